"""Term selection on the integrated likelihood: drops, additions and swaps.

A closed system's terms are chosen by the extended Bayesian information criterion of
its fit by integration: ``misfit / s^2 + k (log(n) + log(p))`` (misfit in noise
variances, ``s^2`` the residual variance, never below 1 so exact data do not make the
integrator's own error look like signal; ``k`` free coefficients, ``n`` data, ``p`` the
pool of terms searched). Greedy backward elimination
alone goes wrong among collinear terms (at 10% noise on prey-only Lotka-Volterra it
drops the real ``x`` and keeps ``x^2`` and ``h^2`` that compensate), so every step
considers dropping a term, adding a candidate, and swapping one for another.

All moves are scored at once on the fit's local quadratic model (Gauss-Newton: the
normal equations at the current point, the segment starts eliminated by their Schur
complement, so each move costs a solve the size of the coefficient count); the best
one is then refitted exactly and kept only if the exact criterion improves.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla

from ._field import ParametricSystem
from ._refine import Fit, Problem

MAX_STEPS = 12
MAX_ATTEMPTS = 3  # exact refits tried per step before giving up


def select_terms(problem: Problem, fit: Fit, candidates, max_steps=MAX_STEPS):
    """Improve the set of free coefficients of ``fit.system`` by BIC; ``candidates``
    (bool, like ``system.free``) are the coefficients that may be added. Returns the
    final fit and the moves made: ("drop"/"add", cell, predicted BIC change) or
    ("swap", (out, in), change)."""
    # extended BIC (Chen & Chen 2008, gamma = 1/2): the price of a term grows with the
    # number of terms it was chosen from, so that searching many candidates does not
    # let one of them in by chance
    pool = int((candidates | fit.system.free).sum())
    price = float(np.log(max(problem.n_data, 2)) + np.log(max(pool, 1)))
    history, tabu = [], set()
    for _ in range(max_steps):
        s2 = max(fit.residual_variance, 1.0)
        model = _Quadratic(problem, fit, candidates & ~fit.system.free)
        base = _bic(fit, s2, price)
        accepted, attempts = False, 0
        for gain, move, keep in model.moves(price, s2):
            if gain <= 1e-6 or attempts >= MAX_ATTEMPTS:
                break
            if move in tabu:
                continue
            attempts += 1
            trial = _refit(problem, fit, model, keep)
            if trial is not None and _bic(trial, s2, price) < base:
                fit = trial
                history.append((*move, float(gain)))
                accepted = True
                break
            tabu.add(move)  # the quadratic model promised more than the exact refit
        if not accepted:
            break
    return fit, history


def _bic(fit, s2, price):
    return fit.cost / s2 + price * fit.system.n_free


def _refit(problem, fit, model, keep):
    """Exact fit with the coefficients ``keep`` (over the model's cells) free."""
    system = fit.system
    free = np.zeros_like(system.free)
    coef = system.coef.copy()
    for on, cell in zip(keep, model.cells, strict=True):
        free[cell] = on
        if not on and system.free[cell]:
            coef[cell] = 0.0
    new = ParametricSystem(system.state_names, system.n_observed, system.features, coef, free)
    try:
        return problem.fit(new, fit.starts)
    except Exception:  # noqa: BLE001 - a move whose system blows up is not taken
        return None


class _Quadratic:
    """The misfit around ``fit`` as a quadratic in the coefficients (current free ones
    and the candidates at zero), starts eliminated."""

    def __init__(self, problem, fit, allowed):
        system = fit.system
        aug = ParametricSystem(system.state_names, system.n_observed, system.features,
                               system.coef, system.free | allowed)
        eq = problem.equations(aug, fit.starts, np.ones(problem.n_segments), fit.rho)
        self.cells = list(zip(*np.nonzero(aug.free), strict=True))
        p = len(self.cells)
        a = eq.matrix().tocsc()
        g = eq.grad
        a_pp = a[:p, :p].toarray()
        a_ps = a[:p, p:].toarray()
        a_ss = a[p:, p:].tocsc()
        if a_ss.shape[0]:
            ridge = 1e-12 * max(float(a_ss.diagonal().max()), 1e-300)
            lu = spla.splu((a_ss + ridge * sps.identity(a_ss.shape[0])).tocsc())
            x = lu.solve(np.column_stack([a_ps.T, g[p:]]))
            self.a = a_pp - a_ps @ x[:, :p]
            self.g = g[:p] - a_ps @ x[:, p]
        else:
            self.a, self.g = a_pp, g[:p]
        self.values = np.array([aug.coef[c] for c in self.cells])
        self.current = np.array([bool(system.free[c]) for c in self.cells])

    def predicted(self, keep):
        """Predicted misfit change when only ``keep`` (bool over cells) is free."""
        removed = self.current & ~keep
        d_r = -self.values[removed]
        a_kk = self.a[np.ix_(keep, keep)]
        rhs = -(self.g[keep] + self.a[np.ix_(keep, removed)] @ d_r)
        try:
            d_k = np.linalg.solve(a_kk + 1e-12 * np.trace(a_kk) * np.eye(len(a_kk)), rhs) \
                if keep.any() else np.zeros(0)
        except np.linalg.LinAlgError:
            return np.inf
        quad = (d_k @ a_kk @ d_k + 2 * d_k @ self.a[np.ix_(keep, removed)] @ d_r
                + d_r @ self.a[np.ix_(removed, removed)] @ d_r)
        return float(2 * (self.g[keep] @ d_k + self.g[removed] @ d_r) + quad)

    def moves(self, price, s2):
        """(BIC gain, move, keep) for every drop, addition and swap, best first."""
        base = self.predicted(self.current)
        k0 = int(self.current.sum())
        inside = np.flatnonzero(self.current)
        outside = np.flatnonzero(~self.current)
        out = []

        def consider(move, keep):
            change = (self.predicted(keep) - base) / s2 + price * (int(keep.sum()) - k0)
            out.append((-change, move, keep))

        for i in inside:
            keep = self.current.copy()
            keep[i] = False
            consider(("drop", self.cells[i]), keep)
        for j in outside:
            keep = self.current.copy()
            keep[j] = True
            consider(("add", self.cells[j]), keep)
            for i in inside:
                swap = keep.copy()
                swap[i] = False
                consider(("swap", (self.cells[i], self.cells[j])), swap)
        out.sort(key=lambda m: -m[0])
        return out
