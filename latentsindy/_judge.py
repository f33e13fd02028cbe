"""The judge: every proposal is closed, refined by integration and scored on held-out data.

For a proposal (:mod:`latentsindy._hypotheses`) the closed system is assembled from
structure (observed terms, hidden states' loadings, the closure's terms), then refined
by multiple shooting (:mod:`latentsindy._refine`) and its terms selected stepwise on
the integrated likelihood: a term is dropped when its Wald statistic ``z^2`` and added
when its score statistic (the misfit it would remove) falls below / exceeds
``log(n)``, the BIC price of a parameter. Last, interleaved held-out segments give its
score. Among all proposals the sparsest one whose score is within one standard error
of the best wins; proposals of the same size within that band make the result
uncertain, and the summary says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sps
import scipy.sparse.linalg as spla
import sympy as sp

from ._field import ParametricSystem
from ._hypotheses import Context, Proposal, close
from ._library import feature_expressions
from ._refine import Fit, Problem, RefineOptions, cross_validate
from ._shooting import BlowUp

MAX_STEPS = 12
RATE_TRIGGER = 1.5  # best misfit (noise variances) above which rate states are tried
TIE = 0.05  # held-out misfits below this (noise variances) cannot be told apart


@dataclass(frozen=True)
class Verdict:
    """A refined, scored proposal."""

    proposal: Proposal
    fit: Fit
    problem: Problem
    cv: float
    cv_se: float
    history: tuple
    initial_misfit: float

    @property
    def system(self) -> ParametricSystem:
        return self.fit.system

    @property
    def scored(self) -> bool:
        """Scored on held-out data (not rejected early, did not blow up)."""
        return not (self.history and isinstance(self.history[0], str))

    @property
    def size(self) -> int:
        """Free coefficients plus hidden initial values."""
        return self.system.n_free + (len(self.system.state_names) - self.system.n_observed)


def build(p: Proposal, ctx: Context):
    """The closed system of a proposal, the terms stepwise selection may add, and the
    initial guesses of the states."""
    st = p.structure
    obs = list(ctx.observed_names)
    hidden = [f"h{a}" for a in range(st.n_hidden)] + (["g0"] if p.order == 2 else [])
    names = obs + hidden
    sym = {n: sp.Symbol(n, real=True) for n in names}
    features, index = [], {}

    def col(expr):
        expr = sp.expand(expr)
        if expr not in index:
            index[expr] = len(features)
            features.append(expr)
        return index[expr]

    obs_cols = [col(e) for e in ctx.feature_exprs]
    closure_states = (["g0"] if p.order == 2 else []) + hidden[:st.n_hidden] + obs
    closure_cols = [col(e) for e in feature_expressions(
        p.closure.library, list(p.closure.feature_names), closure_states)]
    loads = [(i, col(sym[hidden[a]] * ctx.feature_exprs[k]), a, k)
             for i in range(len(obs)) for k in range(st.support.shape[1])
             for a in range(st.n_hidden) if st.loadings[i, k, a] != 0]
    rate = col(sym["g0"]) if p.order == 2 else None
    n = len(names)
    coef = np.zeros((n, len(features)))
    free = np.zeros_like(coef, dtype=bool)
    candidates = np.zeros_like(free)
    for i in range(len(obs)):
        for k in range(st.support.shape[1]):
            if st.support[i, k] and (i, k) not in st.pivots:
                coef[i, obs_cols[k]] = p.fit.constants[i, k]
                free[i, obs_cols[k]] = True
            elif ctx.free_rows[i] and not st.support[i, k]:
                candidates[i, obs_cols[k]] = True
    for i, c, a, k in loads:
        coef[i, c] = st.loadings[i, k, a]
        free[i, c] = (i, k) != st.pivots[a]
    closed = [n - 1] if p.order == 2 else list(range(len(obs), n))
    if rate is not None:
        coef[len(obs), rate] = 1.0  # h0' = g0: the rate state is defined as such
    for r, row in zip(closed, p.closure.coef, strict=True):
        for value, c in zip(row, closure_cols, strict=True):
            if value != 0:
                coef[r, c] = value
                free[r, c] = True
            else:
                candidates[r, c] = True
    system = ParametricSystem(tuple(names), len(obs), tuple(features), coef, free)
    guesses = [np.hstack([x, h]) for x, h in zip(ctx.smoothed, p.hidden, strict=True)]
    return system, candidates & ~free, guesses


@dataclass
class _Trial:
    proposal: Proposal
    problem: Problem
    fit: Fit
    candidates: np.ndarray
    initial_misfit: float


def _first_fit(p: Proposal, ctx: Context, options) -> _Trial | None:
    system, candidates, guesses = build(p, ctx)
    problem = Problem(system, ctx.times, ctx.observed, guesses, options)
    try:
        initial = problem.equations(system, problem.initial_starts,
                                    np.ones(problem.n_segments), 1.0, jacobian=False)
        fit = problem.fit(system)
    except BlowUp:
        return None  # the proposal's system cannot even be integrated from its guesses
    return _Trial(p, problem, fit, candidates, float(np.sqrt(initial.data_cost /
                                                             problem.n_data)))


def _finish(trial: _Trial) -> Verdict:
    """Stepwise selection and the held-out score of a refined proposal."""
    try:
        fit, history = stepwise(trial.problem, trial.fit, trial.candidates)
        cv, se, _ = cross_validate(trial.problem, fit)
    except BlowUp:
        return _unscored(trial, "blew up")
    return Verdict(trial.proposal, fit, trial.problem, cv, se, tuple(history),
                   trial.initial_misfit)


def _unscored(trial: _Trial, why: str) -> Verdict:
    return Verdict(trial.proposal, trial.fit, trial.problem, trial.fit.residual_variance, 0.0,
                   (why,), trial.initial_misfit)


def judge_all(proposals, ctx: Context, options: RefineOptions | None = None):
    """Judge the proposals: refine each; when none reproduces the data to about its
    noise level, also refine the best single-hidden-state proposals with the hidden
    state's rate as a second state; then select terms stepwise and score on held-out
    data those whose in-sample misfit is within twice the best one's (the others
    cannot come close on held-out data). Returns ``rank``'s result."""
    options = options or RefineOptions()
    trials = [t for t in (_first_fit(p, ctx, options) for p in proposals) if t is not None]
    best = min((t.fit.residual_variance for t in trials), default=np.inf)
    if best > RATE_TRIGGER:
        singles = [p for p in proposals if p.structure.n_hidden == 1 and p.order == 1]
        for p in singles[:2]:
            t = _first_fit(close(p.structure, p.fit, ctx, p.origin + ", with its rate", 2),
                           ctx, options)
            if t is not None:
                trials.append(t)
        best = min((t.fit.residual_variance for t in trials), default=np.inf)
    verdicts = []
    for t in trials:
        if t.fit.residual_variance <= 2.0 * max(best, 1.0):
            verdicts.append(_finish(t))
        else:
            verdicts.append(_unscored(t, "rejected"))
    return rank(verdicts)


def stepwise(problem: Problem, fit: Fit, candidates, max_steps=MAX_STEPS):
    """Drop the weakest term while z^2 < log(n); add the best candidate while its score
    statistic exceeds log(n). Returns the final fit and the moves made."""
    price = float(np.log(max(problem.n_data, 2)))
    history, dropped, added = [], set(), set()
    for _ in range(max_steps):
        system = fit.system
        # never trust residuals below the noise level (exact data leave only the
        # integrator's systematic error, which extra terms would chase)
        s2 = max(fit.residual_variance, 1.0)
        values = system.free_values()
        se = np.sqrt(np.maximum(np.diag(fit.covariance), 0.0) * s2)
        cells = list(zip(*np.nonzero(system.free), strict=True))
        if cells:
            z2 = np.where(se > 0, (values / np.where(se > 0, se, 1.0)) ** 2, np.inf)
            z2[[c in added for c in cells]] = np.inf  # no cycles: added terms stay
            k = int(np.argmin(z2))
            if z2[k] < price:
                cell = cells[k]
                free = system.free.copy()
                free[cell] = False
                coef = system.coef.copy()
                coef[cell] = 0.0
                fit = problem.fit(ParametricSystem(system.state_names, system.n_observed,
                                                   system.features, coef, free), fit.starts)
                dropped.add(cell)
                history.append(("drop", cell, float(z2[k])))
                continue
        allowed = candidates & ~system.free
        for cell in dropped:
            allowed[cell] = False
        if not allowed.any():
            break
        gains = score_statistics(problem, fit, allowed)
        cell, gain = max(gains.items(), key=lambda kv: kv[1])
        if gain / s2 <= price:
            break
        free = system.free.copy()
        free[cell] = True
        fit = problem.fit(ParametricSystem(system.state_names, system.n_observed,
                                           system.features, system.coef, free), fit.starts)
        added.add(cell)
        history.append(("add", cell, float(gain / s2)))
    return fit, history


def score_statistics(problem: Problem, fit: Fit, allowed):
    """For every allowed cell: the decrease of the misfit (noise units) that freeing that
    coefficient alone would bring, to first order (Lagrange multiplier test)."""
    system = fit.system
    free = system.free | allowed
    aug = ParametricSystem(system.state_names, system.n_observed, system.features,
                           system.coef, free)
    eq = problem.equations(aug, fit.starts, np.ones(problem.n_segments), fit.rho)
    a = eq.matrix().tocsc()
    g = eq.grad
    cells = list(zip(*np.nonzero(free), strict=True))
    cand = [k for k, c in enumerate(cells) if allowed[c]]
    rest = np.setdiff1d(np.arange(a.shape[0]), cand)
    a_rr = a[rest][:, rest]
    ridge = 1e-10 * max(float(a_rr.diagonal().max()), 1e-300)
    lu = spla.splu((a_rr + ridge * sps.identity(len(rest))).tocsc())
    g_r = lu.solve(g[rest])
    gains = {}
    for k in cand:
        col = a[rest, k].toarray().ravel()
        v = lu.solve(col)
        denom = float(a[k, k] - col @ v)
        num = float(g[k] - col @ g_r)
        gains[cells[k]] = num * num / denom if denom > 0 else 0.0
    return gains


def rank(verdicts):
    """Verdicts ordered by choice: the sparsest within one standard error of the best
    score first; returns (ordered, uncertain) where ``uncertain`` lists the others of
    the same size within that band (structures the data cannot tell apart)."""
    unique = []
    for v in sorted(verdicts, key=lambda v: (not v.scored, v.cv)):
        if not any(same_structure(v, u) for u in unique):
            unique.append(v)  # the same final system reached twice counts once
    verdicts = unique
    finite = [v for v in verdicts if np.isfinite(v.cv)]
    if not finite:
        return sorted(verdicts, key=lambda v: v.size), []
    best = min(finite, key=lambda v: v.cv)
    band = max(best.cv + best.cv_se, TIE)
    inside = [v for v in finite if v.cv <= band]
    chosen = min(inside, key=lambda v: (v.size, v.cv))
    rest = sorted([v for v in verdicts if v is not chosen],
                  key=lambda v: (v.cv > band, v.size if v.cv <= band else 0, v.cv))
    uncertain = [v for v in inside if v is not chosen and v.size <= chosen.size
                 and not same_structure(v, chosen)]
    return [chosen] + rest, uncertain


def same_structure(a: Verdict, b: Verdict) -> bool:
    sa, sb = a.system, b.system
    return (sa.state_names == sb.state_names and sa.features == sb.features
            and np.array_equal(sa.free | (sa.coef != 0), sb.free | (sb.coef != 0)))
