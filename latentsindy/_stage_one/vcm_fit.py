"""The varying-coefficient model of one equation: evidence and posterior of a structure.

A structure is a support S (library columns) and the varying terms V within it; the
other terms of S are constants. On the normal equations of :mod:`.vcm`:

* the second differences of each varying series' B-spline coefficients have the prior
  N(0, s2 / (rough q_m)): a random walk on slopes whose roughness is chosen by the
  evidence (type-II maximum likelihood); with ``adaptive`` the weights q_m get a
  Gamma(nu / 2, nu / 2) prior (a Student-t prior on slope changes: a series is smooth
  where the data allow and bends sharply, or jumps, where they demand it), fitted by
  variational Bayes, and the score is the variational lower bound;
* constants and every series' level are N(0, LEVEL_SD^2) at the measurement noise
  level (broad: ten times the equation's RMS derivative);
* the noise variance s2 is integrated out (Jeffreys prior), so a structure's score is
  a closed form in the roughness alone.

Everything is in the normalised units of stage one. Each evaluation is one banded
Cholesky factorisation; the posterior standard deviation of a series at any time
comes from the entries of the inverse inside the band (selected inversion).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import eig_banded
from scipy.optimize import minimize, minimize_scalar
from scipy.special import digamma, gammaln

from .._core._band_kernels import penalised
from .._core.banded import cholesky_solve, cholesky_upper
from .vcm import ORDER, EquationGram
from .vcm_spread import NoSpread, Spread, covariance, penalty_band

LOG_ROUGH = (-15.0, 25.0)  # bounds of log roughness (relative to the noise precision)
LEVEL_SD = 10.0
NU = 1.0  # degrees of freedom of the adaptive (Student-t) prior on slope changes
EM_STEPS = 5
# A roughness search's line search gives up after LINE_STEPS trials (scipy's default
# is 20). Its gradients are forward differences of a log evidence that carries rounding
# noise of ~1e-5 nats, so they can be wrong by ~1e3 (step 1e-8): a line search that
# has found no decrease in 8 trials (a step shrunk by 2^8 or more) is searching that
# noise, and each trial costs one evaluation per varying term and one more. On
# Hindmarsh-Rose at 5%, draw 0, 222 of 577 searches ended so; at 8 trials stage one
# took 70 s instead of 105, with the same structures and score.
LINE_STEPS = 8


@dataclass(frozen=True)
class EquationFit:
    """A fitted structure of one equation (normalised units).

    Attributes
    ----------
    score : float
        Log evidence (a lower bound with adaptive smoothing); ``-inf`` if singular.
    support, varying, constant : tuple of int
        Library columns in the model; those whose coefficient varies; the others.
    log_rough : ndarray (len(varying),)
    spline : ndarray (n_knots, len(varying))
        Posterior mean of the varying terms' B-spline coefficients.
    constants : ndarray (len(constant),)
    constant_cov : ndarray (len(constant), len(constant))
    noise_variance : float
        Posterior estimate of the noise variance (normalised units).
    adaptive : bool
    spline_cov, edf : computed on first use (see the properties)
    """

    score: float
    support: tuple[int, ...]
    varying: tuple[int, ...]
    constant: tuple[int, ...]
    log_rough: np.ndarray
    spline: np.ndarray
    constants: np.ndarray
    constant_cov: np.ndarray
    noise_variance: float
    adaptive: bool = False
    _posterior: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def spline_cov(self) -> np.ndarray:
        """(4, n_knots, len(varying)): covariance of spline coefficients k and k + d."""
        return self._posterior["spline_cov"]()

    @property
    def edf(self) -> np.ndarray:
        """Effective degrees of freedom of each varying series (2: a straight line)."""
        return self._posterior["edf"]()

    def series(self, first, values, with_sd=True):
        """Posterior mean and standard deviation of every varying term at the times
        of the basis (``vcm.spline_basis``): two (n, len(varying)) arrays (the second
        None without ``with_sd``)."""
        v, n = len(self.varying), len(first)
        mean, var = np.zeros((n, v)), np.zeros((n, v))
        if not v or not np.isfinite(self.score):
            return mean, var
        for a in range(ORDER):
            mean += values[:, a, None] * self.spline[first + a]
        if not with_sd:
            return mean, None
        for a in range(ORDER):
            for b in range(ORDER):
                lo, d = min(a, b), abs(a - b)
                var += (values[:, a] * values[:, b])[:, None] * self.spline_cov[d][first + lo]
        return mean, np.sqrt(np.maximum(var, 0.0))

    def constant_sd(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.constant_cov), 0.0))


def _second_difference_eigenvalues(n_knots):
    """Eigenvalues of D2'D2 (two of them zero)."""
    return np.clip(eig_banded(penalty_band(np.ones(n_knots - 2), n_knots),
                              eigvals_only=True), 0.0, None)


@functools.lru_cache(maxsize=8)
def _difference_band(n):
    """The upper diagonals of D2 D2' (n unknowns) as the banded layout holds them: 1
    two places off the diagonal, -4 one place off (read-only, made once per size)."""
    outer = np.concatenate([np.zeros(2), np.ones(n - 2)])
    next_to = np.concatenate([np.zeros(1), np.full(n - 1, -4.0)])
    outer.flags.writeable = next_to.flags.writeable = False
    return outer, next_to


def _prior_logdet(q, rough, ridge):
    """log det(ridge I + rough D2' Q D2) without the ill-conditioned matrix itself
    (Sylvester's identity: 2 log ridge + log det Q + (m - 2) log rough
    + log det(D2 D2' + ridge / rough Q^-1), a well-conditioned band)."""
    n = len(q)
    outer, next_to = _difference_band(n)
    inner = np.empty((3, n), order="F")  # as LAPACK reads it: factorised in place
    inner[0], inner[1], inner[2] = outer, next_to, 6.0 + ridge / (rough * q)
    chol = cholesky_upper(inner, overwrite=True)
    return (2.0 * np.log(ridge) + float(np.sum(np.log(q))) + n * np.log(rough)
            + 2.0 * float(np.sum(np.log(chol[-1]))))


class _Normal:
    """The normal equations of one structure, assembled once: the varying terms' band
    (interleaved by knot: parameter (m, a) at m v + a), its coupling to the
    constants, the constants' block and the right-hand sides."""

    def __init__(self, g: EquationGram, varying, constant):
        m_knots, v, reach = g.n_knots, len(varying), g.reach
        self.varying, self.constant = varying, constant
        self.width = reach * v
        # Fortran order, as LAPACK reads it: each solve factorises a copy in place
        ab = np.zeros((self.width, m_knots * v), order="F")
        vi, ci = np.asarray(varying, int), np.asarray(constant, int)
        knots = np.arange(m_knots)
        for d in range(reach):
            block = g.band[d][:, vi][:, :, vi]  # element ((m, a), (m + d, b))
            for a in range(v):
                for b in range(0 if d else a, v):
                    col = (knots[: m_knots - d] + d) * v + b
                    ab[self.width - 1 - (d * v + b - a), col] += block[: m_knots - d, a, b]
        self.data_band = ab
        self.cross = g.spline_const[:, vi][:, :, ci].reshape(m_knots * v, len(ci))
        self.cc = g.const[np.ix_(ci, ci)]
        self.with_level: dict = {}  # level -> cc + level I (EquationModel._solve's)
        self.rhs_b = g.spline_y[:, vi].reshape(m_knots * v)
        # both right-hand sides of a solve, solved in one pass (the varying terms' own
        # first, then the constants' coupling): each column as it would be alone
        self.rhs_both = np.column_stack([self.rhs_b, self.cross])
        self.rhs_c = g.const_y[ci]
        # where each varying term's penalty lands in the band flattened in its own
        # (Fortran) order, row + column * width: term a's diagonals d = 0, 1, 2 in
        # turn (unique positions: one += adds them all)
        self.penalty_at = np.concatenate(
            [(self.width - 1 - d * v) + (knots[d:] * v + a) * self.width
             for a in range(v) for d in range(3)]).astype(np.intp) if v else np.zeros(0, np.intp)


class EquationModel:
    """Scores and fits structures of one equation; results are cached per structure.

    Parameters
    ----------
    gram : EquationGram
    noise_variance : float
        The measurement noise variance (normalised units): the scale of the level
        priors.
    """

    def __init__(self, gram: EquationGram, noise_variance: float):
        self.g = gram
        scale = max(float(noise_variance), 1e-300)
        self.noise_variance = scale
        # level priors in units of the noise precision: N(0, LEVEL_SD^2) at s2 = scale
        self.level = scale / LEVEL_SD**2
        self.ridge = self.level / gram.n_knots  # a series' level is the sum of its knots
        self._eig = _second_difference_eigenvalues(gram.n_knots)
        self._uniform = penalty_band(np.ones(gram.n_knots - 2), gram.n_knots)
        self._cache: dict = {}
        # where a list: every structure asked for is appended (the structure search's
        # record, see structure.side_by_side)
        self.looked = None

    def _penalty_rows(self, weights):
        """The penalty band's diagonals d = 0, 1, 2 of every varying term (weights
        ``weights``), laid end to end in the order of :class:`_Normal`'s
        ``penalty_at``, and the term each value belongs to: ``rough[term] * values`` are
        the penalties at roughness ``rough``."""
        rows = []
        for q in weights:
            pen = self._uniform if q is None else penalty_band(q, self.g.n_knots)
            rows += [pen[2 - d, d:] for d in range(3)]
        values = np.concatenate(rows) if rows else np.zeros(0)
        # diagonals of m, m - 1 and m - 2 entries (m knots) for each term
        term = np.repeat(np.arange(len(weights)), 3 * self.g.n_knots - 3)
        return values, term

    def _prior_logdet(self, q, rough):
        if q is None:  # uniform weights: the eigenvalues of D2'D2 give it directly
            return float(np.sum(np.log(rough * self._eig + self.ridge)))
        return _prior_logdet(q, rough, self.ridge)

    def _known_prior_logdet(self, a, q, rough, known):
        """:meth:`_prior_logdet` of varying term ``a`` (weights ``q``), from ``known``
        ({(term, roughness): value} at the caller's fixed weights) where it is there,
        else computed and kept there. A roughness search's forward differences move
        one term's roughness at a time, so every other term's prior is one already
        computed (Hindmarsh-Rose at 5% noise: 40% of the adaptive priors, each a banded
        factorisation)."""
        if known is None:
            return self._prior_logdet(q, rough)
        key = (a, float(rough))
        if key not in known:
            known[key] = self._prior_logdet(q, rough)
        return known[key]

    # ----------------------------------------------------------------- solving
    def _solve(self, st: _Normal, log_rough, weights, rows=None, known=None):
        """Log evidence (noise variance integrated out) and the posterior's pieces;
        None when singular. ``rows``: the weights' penalty diagonals
        (:meth:`_penalty_rows`), where the caller keeps them; ``known``: the
        priors' log-determinants at these weights (:meth:`_known_prior_logdet`), where
        the caller keeps them."""
        g, v = self.g, len(st.varying)
        rough = np.exp(np.clip(np.asarray(log_rough, float), *LOG_ROUGH))
        if v:  # the data's band plus the penalties (in LAPACK's layout: a Fortran copy)
            values, term = self._penalty_rows(weights) if rows is None else rows
            ab = penalised(st.data_band.reshape(-1, order="F"), st.penalty_at, rough, term,
                           values, st.width - 1, self.ridge).reshape(st.data_band.shape, order="F")
        cc = st.with_level.get(self.level)  # the constants' block with their prior
        if cc is None:
            cc = st.with_level[self.level] = st.cc + self.level * np.eye(len(st.constant))
        logdet, u = 0.0, None
        try:
            if v:
                u, both = cholesky_solve(ab, st.rhs_both, overwrite=True)  # ab: its own
                logdet += 2.0 * float(np.sum(np.log(u[-1])))
                sol_b, proj = both[:, 0], both[:, 1:]
                schur = cc - st.cross.T @ proj
                rhs_s = st.rhs_c - st.cross.T @ sol_b
            else:
                sol_b, proj, schur, rhs_s = st.rhs_b, st.cross, cc, st.rhs_c
            w_c, w_b, schur_inv = np.zeros(0), sol_b, np.zeros((0, 0))
            if len(st.constant):
                lc = np.linalg.cholesky(schur)
                logdet += 2.0 * float(np.sum(np.log(np.diag(lc))))
                schur_inv = np.linalg.inv(schur)
                w_c = schur_inv @ rhs_s
                if v:
                    w_b = sol_b - proj @ w_c
            prior = len(st.constant) * np.log(self.level) + sum(
                self._known_prior_logdet(a, weights[a], rough[a], known) for a in range(v))
        except np.linalg.LinAlgError:
            return None
        resid = g.yy - float(st.rhs_b @ w_b + st.rhs_c @ w_c)
        if not resid > 0:
            return None
        n = g.n
        log_ev = (gammaln(0.5 * n) - 0.5 * n * np.log(np.pi) + 0.5 * prior - 0.5 * logdet
                  - 0.5 * n * np.log(resid))
        return float(log_ev), (u, proj, schur_inv, w_b, w_c, rough, resid / n)

    def _optimise(self, st, weights, x0, known=None):
        """Roughness of every varying term by maximum evidence (``known``: as
        :meth:`_solve`'s)."""
        rows = self._penalty_rows(weights)  # fixed while roughness moves

        def objective(z):
            solved = self._solve(st, np.atleast_1d(z), weights, rows, known)
            return 1e300 if solved is None else -solved[0]

        if len(x0) == 1:
            lo, hi = LOG_ROUGH
            res = minimize_scalar(objective, bounds=(lo, hi), method="bounded",
                                  options={"xatol": 0.05})
            return np.array([res.x])
        res = minimize(objective, np.clip(x0, *LOG_ROUGH), method="L-BFGS-B",
                       bounds=[LOG_ROUGH] * len(x0),
                       options={"maxiter": 30, "ftol": 1e-8, "maxls": LINE_STEPS})
        return np.asarray(res.x, float)

    # ------------------------------------------------------------------ fitting
    def fit(self, support, varying, adaptive=False, start=None) -> EquationFit:
        """Fit a structure (cached): roughness by maximum evidence; with ``adaptive``
        also per-knot weights by variational Bayes. ``start``: {term: log roughness}
        to start from (a neighbouring structure's)."""
        key = _structure_key(support, varying, adaptive)
        if self.looked is not None:
            self.looked.append(key)
        if key not in self._cache:
            self._cache[key] = self._fit(*key, start or {})
        return self._cache[key]

    def fitted(self, support, varying, adaptive=False) -> bool:
        """Whether :meth:`fit` has this structure at hand (cached)."""
        return _structure_key(support, varying, adaptive) in self._cache

    def _fit(self, support, varying, adaptive, start):
        constant = tuple(j for j in support if j not in varying)
        v, m_knots = len(varying), self.g.n_knots
        st = _Normal(self.g, varying, constant)
        weights = [None] * v  # None: uniform (Gaussian slope priors)
        log_rough = np.array([start.get(k, 8.0) for k in varying], float)
        if adaptive:  # start from the Gaussian fit
            log_rough = np.array(self.fit(support, varying).log_rough, float)
        solved = None
        for _ in range(EM_STEPS if adaptive else 1):
            known = {}  # the priors' log-determinants at these weights
            if v:
                log_rough = self._optimise(st, weights, log_rough, known)
            solved = self._solve(st, log_rough, weights, known=known)
            if solved is None or not adaptive:
                break
            weights = self._update(st, solved, weights)[0]
        if solved is not None and adaptive:
            solved = self._solve(st, log_rough, weights)
        if solved is None:
            fit = EquationFit(-np.inf, support, varying, constant, log_rough,
                              np.zeros((m_knots, v)), np.zeros(len(constant)),
                              np.zeros((len(constant),) * 2), np.nan, adaptive)
            nothing = NoSpread(m_knots, v)
            fit._posterior.update(spline_cov=nothing.spline_cov, edf=nothing.edf)
            return fit
        log_ev, (u, proj, schur_inv, w_b, w_c, rough, s2) = solved
        spread = Spread(st, solved, m_knots, rough, weights, s2, self.ridge, self._uniform)
        if adaptive:  # the bound's correction needs the covariance: keep it
            log_ev += self._update(st, solved, weights, spread.covariance())[1]
        fit = EquationFit(log_ev, support, varying, constant, log_rough, w_b.reshape(m_knots, v),
                          w_c, schur_inv * s2, s2, adaptive)
        fit._posterior.update(spline_cov=spread.spline_cov, edf=spread.edf)
        return fit

    def _covariance(self, st, solved):
        return covariance(st, solved, self.g.n_knots)

    def _update(self, st, solved, weights, cov=None):
        """Variational step for the knot weights (Gamma posteriors from the expected
        squared slope changes) and the bound's correction to the Gaussian evidence
        evaluated at ``weights``: returns (new weights, correction)."""
        if cov is None:
            cov = self._covariance(st, solved)
        w_b, rough, s2 = solved[1][3], solved[1][5], solved[1][6]
        v, m_knots = len(st.varying), self.g.n_knots
        spline = w_b.reshape(m_knots, v)
        shape = 0.5 * (NU + 1.0)
        new, correction = [], 0.0
        for a in range(v):
            second = spline[:-2, a] - 2 * spline[1:-1, a] + spline[2:, a]
            c0, c1, c2 = cov[0, :, a], cov[1, :, a], cov[2, :, a]
            var = c0[:-2] + 4 * c0[1:-1] + c0[2:] - 4 * c1[:-2] - 4 * c1[1:-1] + 2 * c2[:-2]
            # E[d^2] in units of the noise variance (the prior is N(0, s2 / (rough q)))
            expect = second**2 / s2 + np.maximum(var, 0.0)
            rate = 0.5 * (NU + rough[a] * expect)
            mean_q, log_q = shape / rate, digamma(shape) - np.log(rate)
            kl = ((shape - 0.5 * NU) * digamma(shape) - gammaln(shape) + gammaln(0.5 * NU)
                  + 0.5 * NU * (np.log(rate) - np.log(0.5 * NU))
                  + shape * (0.5 * NU - rate) / rate)
            used = np.ones(m_knots - 2) if weights[a] is None else weights[a]
            correction += float(np.sum(0.5 * (log_q - np.log(used))
                                       - 0.5 * rough[a] * expect * (mean_q - used) - kl))
            new.append(mean_q)
        return new, correction


def _structure_key(support, varying, adaptive):
    """:meth:`EquationModel.fit`'s cache key: sorted term indices, and adaptive priors
    only where something varies."""
    varying = tuple(sorted(int(k) for k in varying))
    return tuple(sorted(int(j) for j in support)), varying, bool(adaptive) and bool(varying)
