"""A proposal judged: its closed system built, refined by integration, its terms
selected and scored on held-out data (:class:`Verdict`).

:func:`build` assembles a proposal's closed system from its structure (observed terms,
hidden states' loadings, the closure's terms); :func:`first_fit` refines it by multiple
shooting (:mod:`.refine`); :func:`finish` selects its terms on the integrated likelihood
(:mod:`.terms`) and scores it on interleaved held-out segments.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import sympy as sp

from .._core.budget import expired, passed, progress
from .._core.library import feature_expressions
from .._core.parallel import map_on, shared_values
from .._core.timing import stage
from .context import Context
from .fit.field import ParametricSystem
from .fit.held_out import cross_validate
from .fit.least_squares import HOPELESS, GiveUpWatch
from .fit.refine import Fit, Problem
from .fit.shooting import BlowUp
from .fit.terms import select_terms
from .fit.windows import judged_part
from .propose.nested import nested_system
from .propose.proposal import Proposal


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
    candidates: np.ndarray | None = None
    # held-out error of each held-out unit (segment, recording or sample: .fit.held_out),
    # the same units in the same order for every verdict of one discovery
    # (:func:`.ranking.rank` pairs them)
    errors: np.ndarray | None = None
    # a verdict judged on the windows of a long recording (``problem``): the recording's
    # whole problem (:func:`on_whole` fits it there where it is chosen)
    whole: Problem | None = None

    @property
    def system(self) -> ParametricSystem:
        return self.fit.system

    @property
    def scored(self) -> bool:
        """Scored on held-out data (not rejected early, did not blow up)."""
        return not (self.history and isinstance(self.history[0], str))

    @property
    def size(self) -> int:
        """Free coefficients plus hidden initial values, one set per recording (of the
        whole data: the windows a long recording is judged on are not recordings)."""
        data = self.problem if self.whole is None else self.whole
        return self.system.n_parameters(len(data.groups))


def closure_state_names(p: Proposal, observed, hidden) -> list[str]:
    """The states the closure library of ``p`` was fitted on, in its order: the rate
    state (second order), the hidden states, the observed ones (``hidden`` as the
    closed system names them, the rate state last)."""
    return (["g0"] if p.order == 2 else []) + list(hidden[:p.structure.n_hidden]) + list(observed)


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
    closure_states = closure_state_names(p, obs, hidden)
    closure_cols = [col(e) for e in feature_expressions(
        p.closure.library, list(p.closure.feature_names), closure_states)] \
        if len(p.closure.coef) else []  # no hidden state: nothing to close
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
class Trial:
    proposal: Proposal
    problem: Problem  # what ``fit`` was made on: the windows of a long recording
    fit: Fit
    candidates: np.ndarray
    initial_misfit: float
    # a long recording's whole problem, where ``problem`` is its windows
    # (:func:`.fit.windows.judged_part`): only the chosen system is fitted on it
    whole: Problem | None = None


def first_fit(p: Proposal, ctx: Context, options, best=np.inf, watch=None) -> Trial | None:
    """``p`` refined; ``best`` is the lowest misfit reached so far: a fit whose first
    pass ends ``HOPELESS`` times above it gets no enforcing pass (it is rejected):
    rejection needs only twice the best, and the enforcing pass only tightens continuity
    (on Lorenz such fits sat at 600-5000 times the best after 40 iterations and spent
    as many again there). ``best`` may be a function that returns it (asked at every
    give-up check); ``watch`` (a :class:`.least_squares.GiveUpWatch`) records the
    checks."""
    system, candidates, guesses = nested_system(p, ctx, build) if p.nested else build(p, ctx)
    give_up = ((lambda: HOPELESS * max(best(), 1.0)) if callable(best)
               else HOPELESS * max(best, 1.0))
    try:
        with stage("refinement"):
            problem, whole = judged_on(Problem(system, ctx.times, ctx.observed, guesses,
                                               options))
            initial = problem.equations(system, problem.initial_starts,
                                        np.ones(problem.n_segments), 1.0, jacobian=False)
            fit = problem.fit(system, give_up=give_up, watch=watch)
    except BlowUp:
        return None  # the proposal's system cannot even be integrated from its guesses
    return Trial(p, problem, fit, candidates,
                 float(np.sqrt(initial.data_cost / problem.n_data)), whole)


def judged_on(problem: Problem):
    """(what a trial on ``problem`` is fitted and judged on, the whole problem or None):
    a long recording's windows (:func:`.fit.windows.judged_part`) and ``problem``,
    where its terms are selected and its score taken; only the system chosen among all
    is then fitted on every sample (:func:`on_whole`); else ``problem`` and None."""
    part = judged_part(problem)
    return (problem, None) if part is None else (part, problem)


def first_fits(proposals, ctx: Context, options, trials=()) -> list[Trial]:
    """:func:`first_fit` of each proposal in order, each given up against the best
    misfit before it (of ``trials`` and the proposals before it); those that blow up
    are left out.

    On a CPU a second process fits some of them side by side (:mod:`.._core.parallel`).
    Each fit then gives up against the best of the fits before it that are known when
    it checks (usually a looser bound than the one-by-one order's: an earlier fit may
    still be running in the other process); its give-up checks are recorded
    (:class:`.least_squares.GiveUpWatch`) and it is kept exactly when the one-by-one bound
    would have given the same fit, else that fit is made again. So the result is the
    loop's, fit for fit, either way. Once the discovery's ``max_time`` is spent, the
    proposals not yet started are left out (recorded, :mod:`.._core.budget`).
    """
    proposals = list(proposals)
    before = min((t.fit.residual_variance for t in trials), default=np.inf)
    found = shared_values(len(proposals))  # misfits as they are found (inf: blew up)

    def side_by_side(k):
        def known():
            earlier = found[:k]
            earlier = earlier[~np.isnan(earlier)]
            return min(before, float(earlier.min())) if earlier.size else before

        if expired():
            return None, None
        progress(lambda: f"first fit {k + 1} of {len(proposals)}: {proposals[k].origin} "
                         f"({proposals[k].n_states} hidden)")
        watch = GiveUpWatch()
        trial = first_fit(proposals[k], ctx, options, known, watch)
        found[k] = np.inf if trial is None else trial.fit.residual_variance
        return trial, watch

    out, best = [], before
    left = 0
    for p, (trial, watch) in zip(proposals, map_on(options.device, side_by_side,
                                                   range(len(proposals))), strict=True):
        if watch is None:  # max_time was spent before it started
            left += 1
            continue
        if not watch.same_under(HOPELESS * max(best, 1.0)) and not expired():
            trial = first_fit(p, ctx, options, best)  # the one-by-one bound stops it sooner
        elif trial is not None:
            trial.proposal = p  # the caller's own (a helper's trial is a copy)
        if trial is not None:
            out.append(trial)
            best = min(best, trial.fit.residual_variance)
    if left:
        passed(f"{left} of {len(proposals)} hypotheses not fitted")
    return out


def finish(trial: Trial) -> Verdict:
    """Stepwise selection and the held-out score of a refined proposal."""
    return finished(trial, selected_and_scored(trial))


def selected_and_scored(trial: Trial):
    """What :func:`finish` computes, in a form that pickles (a helper process can
    compute it, :mod:`latentsindy._core.parallel`): (fit, history, score, standard
    error, held-out errors per held-out unit) after stepwise selection and the held-out
    score, or why there is no score
    ("does not join", "blew up", "not judged": the discovery's ``max_time`` was spent
    before it started or while its folds were refitted).

    A long recording's trial is judged on the windows it was fitted on
    (:func:`first_fit`); its system is fitted on every sample only where it is chosen
    (:func:`on_whole`)."""
    if expired():
        return "not judged"
    # the pool includes the system's own terms, so a term swapped out can come back
    pool = trial.candidates | trial.fit.system.free
    problem = trial.problem
    try:
        fit, history = select_terms(problem, trial.fit, pool)
        if not problem.joins(fit):
            return "does not join"  # not a trajectory of the system
        cv, se, errors = cross_validate(problem, fit)
    except BlowUp:
        return "blew up"
    if expired():  # the folds' refits may have been cut short: not a held-out score
        return "not judged"
    return fit, tuple(history), cv, se, errors


def whole_fit(whole: Problem, rows, fit: Fit) -> Fit:
    """``fit`` (made on the windows of ``whole`` whose segments are ``rows``) fitted on
    every segment of ``whole``: its system, started at its own starts on the windows
    and at the guesses elsewhere. Raises :class:`.fit.shooting.BlowUp`."""
    starts = whole.initial_starts.copy()
    starts[rows] = fit.starts
    with stage("refinement"):
        return whole.fit(fit.system, starts)


def on_whole(verdict: Verdict) -> Verdict | str:
    """A verdict judged on the windows of a long recording (``whole`` set) with its
    system fitted on every sample (:func:`whole_fit`), or why it has none ("blew up",
    "does not join": a scored one's fit must join). A scored verdict keeps its held-out
    score (taken on the windows); an unscored one's ``cv`` is the new fit's in-sample
    misfit."""
    try:
        fit = whole_fit(verdict.whole, verdict.problem.rows, verdict.fit)
        if verdict.scored and not verdict.whole.joins(fit):
            return "does not join"
    except BlowUp:
        return "blew up"
    cv = verdict.cv if verdict.scored else fit.residual_variance
    return replace(verdict, fit=fit, problem=verdict.whole, cv=cv, whole=None)


def finished(trial: Trial, outcome) -> Verdict:
    """The verdict on ``trial`` from :func:`selected_and_scored`'s ``outcome``."""
    if isinstance(outcome, str):
        return unscored(trial, outcome)
    fit, history, cv, se, errors = outcome
    return Verdict(trial.proposal, fit, trial.problem, cv, se, history, trial.initial_misfit,
                   trial.candidates | trial.fit.system.free, errors, trial.whole)


def unscored(trial: Trial, why: str) -> Verdict:
    """A verdict without a held-out score: ``cv`` holds the in-sample misfit (for
    display only; ``rank`` never compares it with held-out scores)."""
    return Verdict(trial.proposal, trial.fit, trial.problem, trial.fit.residual_variance, 0.0,
                   (why,), trial.initial_misfit, whole=trial.whole)

