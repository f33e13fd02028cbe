"""Hidden series under a given structure: a varying-coefficient smoother.

A structure says, for every observed equation, which library terms it has and how the
hidden states enter: ``xdot_i = sum_j c_ij theta_j + sum_k theta_k (c_ik + sum_a
W_ika h_a(t))``, where hidden state ``a`` *is* the coefficient of its pivot term
(``W = 1``, ``c = 0`` there). Given the structure, the hidden series and the constants
follow from penalised least squares in integral form: every observed sample is
predicted by its segment's anchor (a free start value) plus the integral of the
right-hand side from the segment's start, residuals in units of the measurement noise
(no derivative of the noisy data enters). Each h_a is piecewise linear on knots spaced
at half the differentiator's window (the finest scale the data resolve), with a
penalty on its second differences (curvature, which does not shrink amplitudes) whose
weight is the largest that still fits the data as well as their noise allows
(discrepancy principle). Loadings W of non-pivot terms are updated
in alternation. Everything is sparse: cost and memory grow linearly with the series.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sps
from scipy.sparse.linalg import spsolve

from ..._core.fingerprint import fingerprint
from ..._core.local_fits import positions

_LAMBDAS = np.logspace(-6, 4, 11)  # relative curvature weights searched
RELAX = 2.0  # over-relaxation of the loadings' alternating updates (see _update_loadings)


@dataclass(frozen=True)
class Structure:
    """Terms of the observed equations and how hidden states enter them.

    Attributes
    ----------
    support : bool array (n_observed, n_features)
        Terms of each equation (constant or varying).
    loadings : float array (n_observed, n_features, n_hidden)
        Loading of each term's coefficient on each hidden state (0: constant term).
    pivots : tuple of (equation, feature) index pairs, one per hidden state
    """

    support: np.ndarray
    loadings: np.ndarray
    pivots: tuple

    @property
    def n_hidden(self) -> int:
        return len(self.pivots)

    @property
    def varying(self) -> np.ndarray:
        return np.any(self.loadings != 0, axis=-1) & self.support

    def key(self):
        """A hashable description (support, which terms load on what, pivots)."""
        return (self.support.tobytes(), (self.loadings != 0).tobytes(), self.pivots)


@dataclass(frozen=True)
class HiddenFit:
    """Constants, loadings and hidden series that a structure implies."""

    structure: Structure
    constants: np.ndarray  # (n_observed, n_features); offsets of varying terms included
    hidden: list  # (T, n_hidden) per trajectory
    misfit: float  # mean squared residual of the observed samples, in noise variances
    roughness: float


def single_term(n_observed, n_features, equation, feature, support):
    """Structure with one hidden state: the coefficient of ``feature`` in ``equation``."""
    loads = np.zeros((n_observed, n_features, 1))
    loads[equation, feature, 0] = 1.0
    sup = np.array(support, dtype=bool, copy=True)
    sup[equation, feature] = True
    return Structure(sup, loads, ((equation, feature),))


def fit_hidden(structure, thetas, observed, times, sigma, spacing, iterations=5):
    """Estimate constants, non-pivot loadings and hidden series for ``structure``.

    Parameters
    ----------
    thetas : list over trajectories of (T, F)
        The library on the (smoothed) observed states.
    observed : list of (T, n)
        The observed states as measured.
    times : list of (T,)
    sigma : (n,) measurement noise standard deviation of each observed state
    spacing : int or list of int
        Knot spacing in mean sample steps of each trajectory (in time, for irregular
        sampling); one number for all, or one per trajectory.
    """
    st = structure
    data = _Data(thetas, observed, times, sigma, spacing)
    for _ in range(iterations if np.any(_free_loadings(st)) else 1):
        consts, hidden, misfit, rough = _solve(st, data)
        if not np.any(_free_loadings(st)):
            break
        st = _update_loadings(st, data, hidden)
    return HiddenFit(st, consts, hidden, misfit, rough)


def prune_constants(fit, thetas, observed, times, sigma, spacing, threshold, free_rows):
    """Drop constant terms that explain less than ``threshold`` of their equation's RMS
    rate (normalised size), refitting until nothing changes (STLSQ with the smoother
    inside). Rows not in ``free_rows`` keep their terms."""
    theta_rms = np.sqrt(np.mean(np.vstack(thetas) ** 2, axis=0))
    rate_rms = np.sqrt(np.mean(np.vstack([np.gradient(x, t, axis=0) for x, t in
                                          zip(observed, times, strict=True)]) ** 2, axis=0))
    for _ in range(10):
        st = fit.structure
        size = np.abs(fit.constants) * theta_rms[None, :] / np.maximum(rate_rms[:, None],
                                                                       1e-300)
        drop = st.support & ~st.varying & (size < threshold) & free_rows[:, None]
        if not drop.any():
            return fit
        st = replace(st, support=st.support & ~drop)
        fit = fit_hidden(st, thetas, observed, times, sigma, spacing)
    return fit


def _free_loadings(st):
    free = st.loadings != 0
    for a, (i, k) in enumerate(st.pivots):
        free[i, k, a] = False
    return free


class _Data:
    """Per trajectory: the segment-integral operator, anchors, knot interpolation."""

    def __init__(self, thetas, observed, times, sigma, spacing):
        self.thetas = [np.asarray(th, float) for th in thetas]
        self.observed = [np.asarray(x, float) for x in observed]
        self.sigma = np.asarray(sigma, float)
        self.n_obs = self.observed[0].shape[1]
        spacings = ([spacing] * len(self.observed) if np.ndim(spacing) == 0
                    else [int(s) for s in spacing])
        self.integral, self.anchors, self.interp = (
            list(ops) for ops in zip(*_operators(times, spacings), strict=True))
        self.n_rows = sum(x.size for x in self.observed)
        self.n_anchors = sum(a.shape[1] for a in self.anchors) * self.n_obs

    def target(self):
        return np.concatenate([(x / self.sigma).T.ravel() for x in self.observed])


# The operators of the last few calls' sampling (times and knot spacing): the proposals
# fit several structures on the same recordings, and on a long recording building the
# integral operator (a lower triangle per segment: 2 million entries at 20,000 samples)
# cost half of each fit (prey-only LV at 20,000 samples: 0.46 of 0.84 s in 8 fits).
_OPERATORS: dict = {}
_KEEP = 2


def _operators(times, spacings):
    """Per trajectory (sample times ``times``, knot spacing ``spacings``): the
    segment-integral operator, the anchors' indicator and the knots' interpolation,
    made once for the same times and spacings (and shared: never modified)."""
    times = [np.ascontiguousarray(t, dtype=float) for t in times]
    key = tuple((t.tobytes(), s) for t, s in zip(times, spacings, strict=True))
    found = _OPERATORS.get(key)
    if found is None:
        found = [_trajectory_operators(t, s) for t, s in zip(times, spacings, strict=True)]
        _make_room(_OPERATORS, _KEEP)
        _OPERATORS[key] = found
    return found


def _make_room(kept: dict, keep: int):
    """Drop the oldest entries of ``kept`` until fewer than ``keep`` are left; another
    thread may drop them at the same time (no lock: a helper forked while a thread
    held one would wait on it forever)."""
    while len(kept) >= keep:
        try:
            kept.pop(next(iter(kept)), None)
        except (StopIteration, RuntimeError):  # emptied, or changed, meanwhile
            continue


def _trajectory_operators(t, spacing):
    """:func:`_operators` of one trajectory."""
    n = len(t)
    length = int(np.clip(4 * spacing, 16, 200))
    seg = np.minimum(np.arange(n) // length, max((n - 1) // length, 0))
    if n - np.searchsorted(seg, seg[-1]) < length // 2 and seg[-1] > 0:
        seg[seg == seg[-1]] = seg[-1] - 1  # no short last segment
    half = np.diff(np.asarray(t, float)) / 2
    trap = sps.diags([np.append(half, 0.0), half], [0, 1], shape=(n - 1, n))
    # cumulative sum of the increments since the start of each segment
    rows, cols = [], []
    for s0 in np.flatnonzero(np.r_[True, seg[1:] != seg[:-1]]):
        s1 = int(np.searchsorted(seg, seg[s0], side="right"))
        r, c = np.tril_indices(s1 - s0 - 1)
        rows.append(s0 + 1 + r)
        cols.append(s0 + c)
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    cum = sps.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n - 1))
    integral = (cum @ trap).tocsr()
    anchors = sps.csr_matrix((np.ones(n), (np.arange(n), seg)), shape=(n, int(seg.max()) + 1))
    interp = _knots(n, spacing, positions(t))[1]
    return integral, anchors, interp


def _knots(n_times, spacing, where=None):
    """Knots every ``spacing`` mean sample steps in time and the (T, K) linear
    interpolation matrix; ``where`` are the sample times in mean steps (None: uniform,
    the sample indices), so knots are equally spaced in time for any sampling."""
    where = np.arange(n_times) if where is None else where
    grid = np.arange(0, where[-1] + 1, max(1, spacing))
    # none past the last sample (irregular positions end a rounding error short of n - 1)
    knots = np.unique(np.concatenate([grid[grid <= where[-1]], [where[-1]]]))
    j = np.clip(np.searchsorted(knots, where, side="right") - 1, 0, len(knots) - 2)
    w = (where - knots[j]) / (knots[j + 1] - knots[j])
    rows = np.repeat(np.arange(n_times), 2)
    cols = np.stack([j, j + 1], axis=1).ravel()
    vals = np.stack([1 - w, w], axis=1).ravel()
    return knots, sps.csr_matrix((vals, (rows, cols)), shape=(n_times, len(knots)))


# The weighted integrals ``q @ diag(g) @ interp`` of the last few designs, by the
# operators and the weights: the proposals fit several structures whose hidden state
# loads on the same term alone (the same weights g), and on a long recording each
# product is a pass over the integral operator (prey-only LV at 20,000 samples: 8
# products, 3 distinct, 31 ms each). Kept only while their operators are (an operator
# of 20,000 samples holds 24 MB), the least recently used dropped first; shared, never
# modified.
_PRODUCTS: dict = {}
_KEEP_PRODUCTS = 32


def _weighted_integral(q, g, interp):
    """``q @ sps.diags(g) @ interp``, made once for the same operators and weights."""
    key = (id(q), id(interp), *fingerprint(g))
    found = _PRODUCTS.pop(key, None)
    if found is None or found[0] is not q or found[1] is not interp:
        found = (q, interp, q @ sps.diags(g) @ interp)  # (holding q and interp holds ids)
        held = {id(ops[0]) for entry in list(_OPERATORS.values()) for ops in entry}
        for old, value in list(_PRODUCTS.items()):
            if id(value[0]) not in held:
                _PRODUCTS.pop(old, None)
        _make_room(_PRODUCTS, _KEEP_PRODUCTS)
    _PRODUCTS[key] = found  # (again) the most recent
    return found[2]


def _design(st, data: _Data):
    """Weighted design: rows (trajectory, equation, sample); columns [constants | knots
    of each hidden state per trajectory | anchors per trajectory, equation, segment]."""
    n_obs, n_feat = st.support.shape
    const_idx = [(i, j) for i in range(n_obs) for j in range(n_feat)
                 if st.support[i, j] and (i, j) not in st.pivots]
    n_knots = [b.shape[1] for b in data.interp]
    n_anch = [a.shape[1] for a in data.anchors]
    n_hid = st.n_hidden
    total_knots = sum(n_knots) * n_hid
    blocks = []
    k_off, a_off = 0, 0
    for k, (th, q, anchors, interp) in enumerate(zip(data.thetas, data.integral, data.anchors,
                                                    data.interp, strict=True)):
        for i in range(n_obs):
            inv = 1.0 / data.sigma[i]
            c = np.zeros((len(th), len(const_idx)))
            for col, (ii, j) in enumerate(const_idx):
                if ii == i:
                    c[:, col] = q @ th[:, j] * inv
            hid = [sps.csr_matrix((len(th), k_off))]
            for a in range(n_hid):
                g = (th * st.loadings[i, :, a][None, :]).sum(axis=1)
                hid.append(_weighted_integral(q, g, interp) * inv)
            hid.append(sps.csr_matrix((len(th), total_knots - k_off - n_hid * n_knots[k])))
            anch = [sps.csr_matrix((len(th), a_off)), anchors * inv,
                    sps.csr_matrix((len(th), sum(n_anch) * n_obs - a_off - n_anch[k]))]
            blocks.append(sps.hstack([sps.csr_matrix(c), *hid, *anch]))
            a_off += n_anch[k]
        k_off += n_hid * n_knots[k]
    design = sps.vstack(blocks).tocsc()
    penalty = [sps.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(max(nk - 2, 0), nk))
               for nk in n_knots for _a in range(n_hid)]
    pen = None
    if penalty and total_knots:
        pen = sps.block_diag(penalty, format="csc")
        pen = sps.hstack([sps.csc_matrix((pen.shape[0], len(const_idx))), pen,
                          sps.csc_matrix((pen.shape[0], sum(n_anch) * n_obs))]).tocsc()
    return design, pen, const_idx, n_knots


def _solve(st, data: _Data):
    design, pen, const_idx, n_knots = _design(st, data)
    target = data.target()
    gram = (design.T @ design).tocsc()
    rhs = design.T @ target
    n_eff = max(data.n_rows - data.n_anchors - len(const_idx), 1)
    if pen is None or pen.shape[0] == 0:
        sol = _sparse_solve(gram, rhs)
        misfit = float(np.sum((design @ sol - target) ** 2)) / n_eff
        rough = 0.0
    else:
        pgram = (pen.T @ pen).tocsc()
        knots = slice(len(const_idx), len(const_idx) + sum(n_knots) * st.n_hidden)
        scale = gram.diagonal()[knots].mean() / max(pgram.diagonal()[knots].mean(), 1e-300)

        def at(k):  # solution and misfit at the k-th weight of the grid
            sol = _sparse_solve(gram + _LAMBDAS[k] * scale * pgram, rhs)
            return sol, float(np.sum((design @ sol - target) ** 2)) / n_eff

        # white measurement noise: the misfit of a right model is about 1, and
        # fluctuates by sqrt(2 / n); take the smoothest series within that of the
        # attainable misfit (bisection on the grid: the misfit grows with the weight)
        lo, hi = 0, len(_LAMBDAS) - 1
        sol, misfit = at(lo)
        limit = max(misfit, 1.0) * (1.0 + 2.0 * np.sqrt(2.0 / n_eff))
        smooth = at(hi)
        if smooth[1] <= limit:
            sol, misfit = smooth
        else:
            while hi - lo > 1:
                mid = (lo + hi) // 2
                trial = at(mid)
                if trial[1] <= limit:
                    lo, (sol, misfit) = mid, trial
                else:
                    hi = mid
        rough = float(np.sum((pen @ sol) ** 2))
    consts = np.zeros(st.support.shape)
    for col, (i, j) in enumerate(const_idx):
        consts[i, j] = sol[col]
    hidden, pos = [], len(const_idx)
    for interp, nk in zip(data.interp, n_knots, strict=True):
        cols = []
        for _a in range(st.n_hidden):
            cols.append(interp @ sol[pos:pos + nk])
            pos += nk
        hidden.append(np.column_stack(cols) if cols else np.zeros((interp.shape[0], 0)))
    return consts, hidden, misfit, rough


def _update_loadings(st, data: _Data, hidden):
    """Least squares of the loadings of non-pivot varying terms (with the constants and
    anchors of their equations) given the hidden series."""
    free = _free_loadings(st)
    loads = st.loadings.copy()
    for i in range(st.support.shape[0]):
        if not free[i].any():
            continue
        const = [j for j in np.flatnonzero(st.support[i]) if (i, j) not in st.pivots]
        pairs = [tuple(p) for p in np.argwhere(free[i])]
        blocks, targets = [], []
        n_anch = sum(a.shape[1] for a in data.anchors)
        a_off = 0
        for th, x, q, anchors, h in zip(data.thetas, data.observed, data.integral,
                                        data.anchors, hidden, strict=True):
            fixed = np.zeros(len(th))
            for a, (pi, pk) in enumerate(st.pivots):
                if pi == i:
                    fixed += th[:, pk] * h[:, a]
            cols = [q @ th[:, j] for j in const] + [q @ (th[:, k] * h[:, a]) for k, a in pairs]
            dense = np.column_stack(cols)
            anch = sps.hstack([sps.csr_matrix((len(th), a_off)), anchors,
                               sps.csr_matrix((len(th), n_anch - a_off - anchors.shape[1]))])
            blocks.append(sps.hstack([sps.csr_matrix(dense), anch]))
            targets.append(x[:, i] - q @ fixed)
            a_off += anchors.shape[1]
        a_mat = sps.vstack(blocks).tocsc()
        coef = _sparse_solve((a_mat.T @ a_mat).tocsc(), a_mat.T @ np.concatenate(targets))
        for (k, a), value in zip(pairs, coef[len(const):len(const) + len(pairs)], strict=True):
            # over-relaxed: alternating least squares on a bilinear model converges
            # linearly, slowly; stepping twice as far cuts the iterations needed 3-fold
            loads[i, k, a] += RELAX * (value - loads[i, k, a])
    return replace(st, loadings=loads)


def _sparse_solve(matrix, rhs):
    """Solve with Jacobi scaling (columns of very different sizes, e.g. x and x^3) and a
    tiny ridge.

    The scaling ``D M D`` is applied to the stored entries and the ridge added on the
    diagonal in place: for a matrix without duplicate entries (every caller's: products
    and sums of sparse matrices), the same numbers as ``diags(d) @ M @ diags(d) + 1e-10
    I`` built as sparse products, bit for bit, without building three sparse matrices."""
    d = 1.0 / np.sqrt(np.maximum(matrix.diagonal(), 1e-300))
    scaled = sps.csc_matrix(matrix, copy=True)
    scaled.sum_duplicates()
    cols = np.repeat(np.arange(scaled.shape[1]), np.diff(scaled.indptr))
    scaled.data = (d[scaled.indices] * scaled.data) * d[cols]
    on_diagonal = scaled.indices == cols
    if np.count_nonzero(on_diagonal) == scaled.shape[0]:  # every diagonal entry stored
        scaled.data[on_diagonal] += 1e-10
    else:
        scaled = scaled + 1e-10 * sps.identity(scaled.shape[0], format="csc")
    scaled.eliminate_zeros()
    return d * spsolve(scaled, d * rhs)
