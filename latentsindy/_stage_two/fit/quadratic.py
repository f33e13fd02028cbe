"""The misfit of a closed system's fit as a quadratic in its coefficients: the moves of
term selection (:mod:`.terms`) scored without refitting.

Around a fit, the Gauss-Newton normal equations (the segment starts eliminated by their
Schur complement) predict the misfit of every set of free coefficients by one solve the
size of that set. Term selection scores thousands of sets per step (every drop,
addition, swap and merge; every two-for-two exchange), so they are scored side by side:
sets of the same size, with the same number of coefficients removed, form one stack,
and each product and solve runs over the stack. Each set's arithmetic is its own
(the same LAPACK solve, BLAS products and reductions on the same operands), so a
stacked prediction is the one-at-a-time prediction to the bit; the stacks only save
numpy's per-call cost, which at a few microseconds a call was most of the search on a
library of many candidates.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla

from .field import ParametricSystem
from .normal_equations import ArrowMatrix

RIDGE = 1e-12  # of the trace, on the kept block's diagonal: a singular block still solves
STACK = 1 << 19  # matrix entries in one stack of sets (4 MB of float64 a copy)


def solve_starts(a_ss, rhs):
    """``a_ss^-1 rhs`` for the starts' block of small normal equations (a sparse LU)."""
    return spla.splu(a_ss.tocsc()).solve(rhs)


def _eliminated(a, g, p):
    """The coefficients' Schur complement and reduced gradient of the normal equations
    ``a`` (dense, or an :class:`.normal_equations.ArrowMatrix` beyond a hundred unknowns,
    eliminated through the starts' band), the starts' block ridged by ``1e-12`` of its
    largest diagonal entry (a singular block still solves)."""
    if isinstance(a, ArrowMatrix):
        a_pp, a_ps = a.border, a.coupling.reshape(a.k * a.n, p).T
        ridge = np.full(a.k * a.n, 1e-12 * max(float(a.diag.diagonal(axis1=1, axis2=2).max(
            initial=0.0)), 1e-300))
        rhs = np.column_stack([a_ps.T, g[p:]])
        try:
            x = a.starts_solve(rhs, ridge)
        except np.linalg.LinAlgError:
            a_ss = a.tosparse()[p:, p:] + sps.diags(ridge, format="csc")
            x = spla.splu(a_ss.tocsc()).solve(rhs)
        return a_pp - a_ps @ x[:, :p], g[:p] - a_ps @ x[:, p]
    a = sps.csc_matrix(a)
    a_pp = a[:p, :p].toarray()
    a_ps = a[:p, p:].toarray()
    a_ss = a[p:, p:].tocsc()
    if not a_ss.shape[0]:
        return a_pp, g[:p]
    ridge = 1e-12 * max(float(a_ss.diagonal().max()), 1e-300)
    x = solve_starts(a_ss + ridge * sps.identity(a_ss.shape[0]), np.column_stack([a_ps.T, g[p:]]))
    return a_pp - a_ps @ x[:, :p], g[:p] - a_ps @ x[:, p]


class Quadratic:
    """The misfit around ``fit`` as a quadratic in the coefficients (current free ones
    and the candidates ``allowed`` at zero), starts eliminated."""

    def __init__(self, problem, fit, allowed):
        system = fit.system
        aug = ParametricSystem(system.state_names, system.n_observed, system.features,
                               system.coef, system.free | allowed)
        eq = problem.equations(aug, fit.starts, np.ones(problem.n_segments), fit.rho)
        self.cells = list(zip(*np.nonzero(aug.free), strict=True))
        p = len(self.cells)
        self.a, self.g = _eliminated(eq.matrix(), eq.grad, p)
        self.values = np.array([aug.coef[c] for c in self.cells], dtype=float)
        self.current = np.array([bool(system.free[c]) for c in self.cells], dtype=bool)

    def predicted(self, keep):
        """Predicted misfit change when only ``keep`` (bool over cells) is free."""
        return self._solve(keep)[0]

    def predicted_many(self, keeps):
        """:meth:`predicted` of each row of ``keeps`` (bool, sets x cells), the same to
        the bit, the sets of one size and one count of removed cells side by side."""
        keeps = np.atleast_2d(np.asarray(keeps, dtype=bool))
        out = np.empty(len(keeps))
        if not len(keeps):
            return out
        removed = self.current & ~keeps
        sizes = np.stack([keeps.sum(axis=1), removed.sum(axis=1)], axis=1)
        shapes, which = np.unique(sizes, axis=0, return_inverse=True)
        for s, (n_keep, n_removed) in enumerate(shapes):
            # stacks of at most STACK matrix entries: memory stays a few MB however
            # many sets a large library makes
            per_set = (n_keep + n_removed) ** 2 + 1
            every = np.flatnonzero(which.reshape(-1) == s)
            stacks = min(len(every), -(-len(every) * per_set // STACK))
            for rows in np.array_split(every, stacks):
                kept = np.nonzero(keeps[rows])[1].reshape(len(rows), n_keep)
                gone = np.nonzero(removed[rows])[1].reshape(len(rows), n_removed)
                try:
                    out[rows] = self._stacked(kept, gone)
                except np.linalg.LinAlgError:  # a singular set in the stack: one at a time
                    out[rows] = [self.predicted(keeps[r]) for r in rows]
        return out

    def values_after(self, keep):
        """The coefficients (over cells) at the model's minimum with only ``keep`` free:
        the start of the exact refit (kept terms already compensate for removed ones)."""
        step = self._solve(keep)[1]
        values = np.where(keep, self.values, 0.0)
        if step is not None:
            values[keep] += step
        return values

    def _solve(self, keep):
        removed = self.current & ~keep
        d_r = -self.values[removed]
        a_kk = self.a[np.ix_(keep, keep)]
        rhs = -(self.g[keep] + self.a[np.ix_(keep, removed)] @ d_r)
        try:
            d_k = np.linalg.solve(a_kk + RIDGE * np.trace(a_kk) * np.eye(len(a_kk)), rhs) \
                if keep.any() else np.zeros(0)
        except np.linalg.LinAlgError:
            return np.inf, None
        quad = (d_k @ a_kk @ d_k + 2 * d_k @ self.a[np.ix_(keep, removed)] @ d_r
                + d_r @ self.a[np.ix_(removed, removed)] @ d_r)
        return float(2 * (self.g[keep] @ d_k + self.g[removed] @ d_r) + quad), d_k

    def _stacked(self, kept, gone):
        """:meth:`_solve`'s prediction for a stack of sets: ``kept`` and ``gone`` (sets x
        size) index the kept and the removed cells. Each product is numpy's own on each
        set (a vector times a matrix, a dot product); raises LinAlgError on a singular
        kept block."""
        a, g = self.a, self.g
        d_r = -self.values[gone]
        a_kk = a[kept[:, :, None], kept[:, None, :]]
        a_kr = a[kept[:, :, None], gone[:, None, :]]
        a_rr = a[gone[:, :, None], gone[:, None, :]]
        rhs = -(g[kept] + (a_kr @ d_r[:, :, None])[:, :, 0])
        n_keep = kept.shape[1]
        if n_keep:
            ridge = (RIDGE * np.trace(a_kk, axis1=1, axis2=2))[:, None, None]
            d_k = np.linalg.solve(a_kk + ridge * np.eye(n_keep), rhs[:, :, None])[:, :, 0]
        else:
            d_k = np.zeros((len(kept), 0))

        def dot(u, v):  # u @ v for each set's vectors
            return (u[:, None, :] @ v[:, :, None])[:, 0, 0]

        quad = (dot((d_k[:, None, :] @ a_kk)[:, 0], d_k)
                + dot(((2 * d_k)[:, None, :] @ a_kr)[:, 0], d_r)
                + dot((d_r[:, None, :] @ a_rr)[:, 0], d_r))
        return 2 * (dot(g[kept], d_k) + dot(g[gone], d_r)) + quad

    def moves(self, price, s2):
        """(BIC gain, move, keep) for every drop, addition, swap and merge, best
        first."""
        base = self.predicted(self.current)
        k0 = int(self.current.sum())
        inside = np.flatnonzero(self.current)
        outside = np.flatnonzero(~self.current)
        listed = []
        for i in inside:
            keep = self.current.copy()
            keep[i] = False
            listed.append((("drop", self.cells[i]), keep))
        for j in outside:
            keep = self.current.copy()
            keep[j] = True
            listed.append((("add", self.cells[j]), keep))
            for a, i in enumerate(inside):
                swap = keep.copy()
                swap[i] = False
                listed.append((("swap", (self.cells[i], self.cells[j])), swap))
                for i2 in inside[a + 1:]:
                    merge = swap.copy()
                    merge[i2] = False
                    listed.append((("merge", ((self.cells[i], self.cells[i2]),
                                              self.cells[j])), merge))
        return self._ranked(listed, base, s2, price, k0)

    def additions(self, price, s2):
        """(BIC gain, move, keep) for adding each candidate alone."""
        base = self.predicted(self.current)
        listed = []
        for j in np.flatnonzero(~self.current):
            keep = self.current.copy()
            keep[j] = True
            listed.append((("add", self.cells[j]), keep))
        return self._ranked(listed, base, s2, price, int(self.current.sum()), order=False)

    def pairs(self, price, s2):
        """(BIC gain, move, keep) for adding every two candidates of one equation
        together, best first. A law whose terms act only together is reached this way:
        a logistic rate ``a + b h + c h^2`` (two fixed points) from ``c h^2``, where
        ``a`` or ``b`` alone moves a fixed point the data do not show."""
        base = self.predicted(self.current)
        listed = []
        for row in sorted({cell[0] for cell in self.cells}):
            outside = [j for j in np.flatnonzero(~self.current) if self.cells[j][0] == row]
            for b, j in enumerate(outside):
                for j2 in outside[b + 1:]:
                    keep = self.current.copy()
                    keep[[j, j2]] = True
                    listed.append((("add pair", (self.cells[j], self.cells[j2])), keep))
        return self._ranked(listed, base, s2, price, int(self.current.sum()))

    def exchanges(self, s2):
        """(gain, move, keep) for every exchange of two terms of one equation for two
        others of that equation (the same size; misfit change only), best first."""
        base = self.predicted(self.current)
        listed = []
        for row in sorted({cell[0] for cell in self.cells}):
            here = np.array([cell[0] == row for cell in self.cells])
            inside = np.flatnonzero(self.current & here)
            outside = np.flatnonzero(~self.current & here)
            for a, i in enumerate(inside):
                for i2 in inside[a + 1:]:
                    for b, j in enumerate(outside):
                        for j2 in outside[b + 1:]:
                            keep = self.current.copy()
                            keep[[i, i2]] = False
                            keep[[j, j2]] = True
                            listed.append((("exchange", ((self.cells[i], self.cells[i2]),
                                                         (self.cells[j], self.cells[j2]))),
                                           keep))
        return self._ranked(listed, base, s2, None, 0)

    def _ranked(self, listed, base, s2, price, k0, order=True):
        """(gain, move, keep) for ``listed`` (move, keep): the gain is the fall of the
        criterion (misfit in ``s2`` plus ``price`` a term; the misfit alone where
        ``price`` is None) from ``base``; best first (a stable sort: ties keep their
        listed order) unless ``order`` is False."""
        if not listed:
            return []
        keeps = np.array([keep for _, keep in listed])
        predicted = self.predicted_many(keeps)
        out = []
        for (move, keep), value in zip(listed, predicted.tolist(), strict=True):
            if price is None:
                out.append((-(value - base) / s2, move, keep))
                continue
            change = (value - base) / s2 + price * (int(keep.sum()) - k0)
            out.append((-change, move, keep))
        if order:
            out.sort(key=lambda m: -m[0])
        return out
