"""From judged proposals to a :class:`HiddenDiscovery` (names, terms, series, alternatives)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import sympy as sp

from .._core.budget import left_out, spent
from .._core.doubt import Doubt
from .._core.parallel import map_on
from .._core.timing import timed
from .doubts.beyond import beyond_terms
from .doubts.checks import doubts, reproduces, segment_constant_doubts, weak_check_doubts
from .doubts.folded import folded_doubts, folded_score
from .doubts.runs import free_run_doubt
from .doubts.states import (
    first_integral_doubt,
    observed_function_doubts,
    partial_shift_doubts,
    redundant_state_doubts,
    unresolved_doubts,
)
from .doubts.terms import (
    beyond_doubts,
    exchange_doubts,
    exchangeable_terms,
    missing_doubts,
    nearly_needed_terms,
    weak_doubts,
    weakly_supported_terms,
)
from .fit.expected_score import REFERENCE, REPLICATES, expected_score
from .fit.held_out import by_recording
from .fit.shooting import BlowUp
from .fit.windows import WINDOWS, judged_part
from .judge import build
from .propose.nested import monomial_name
from .result import HiddenDiscovery
from .result_parts import Alternative, HiddenState, Refinement, Term

NOT_CHECKED = Doubt("not checked",
                    "not refined by integration (refine=False): the structure was chosen by "
                    "its closure's held-out error and was never checked by integrating it "
                    "against the data")


def hidden_names(system, n_observed, given, observed):
    """User-facing names of a system's hidden states: the given ones in order, then
    ``h0, h1, ...``; a rate state defaults to ``<base>_rate``."""
    internal = system.state_names[n_observed:]
    names, taken = [], set(observed)
    given = list(given or [])
    for k, name in enumerate(internal):
        if k < len(given):
            new = given[k]
        elif name.startswith("g"):
            new = f"{names[0]}_rate"
        else:
            new = next(f"h{j}" for j in range(k, k + 100) if f"h{j}" not in taken)
        while new in taken:
            new += "_"
        taken.add(new)
        names.append(new)
    return names


def describe(system, ctx, names, pivots, nested=()):
    """HiddenState of every hidden state of ``system`` (in user names) and the renaming
    map of symbols. ``nested``: :attr:`.proposal.Proposal.nested`, the hidden states
    defined as a coefficient in the previous hidden state's equation."""
    n_obs = system.n_observed
    internal = system.state_names[n_obs:]
    rename = {sp.Symbol(a, real=True): sp.Symbol(b, real=True)
              for a, b in zip(internal, names, strict=True)}
    column = {f: c for c, f in enumerate(system.features)}
    states = []
    for a, name in enumerate(internal):
        if name.startswith("g"):
            states.append(HiddenState(names[a], (), names[0]))
            continue
        if a >= len(pivots):  # inside the previous hidden state's equation
            _, carrier, _ = nested[a - len(pivots)]
            symbols = system.symbols
            carrier = monomial_name(carrier.xreplace(rename), [s.xreplace(rename)
                                                              for s in symbols])
            states.append(HiddenState(names[a], ((names[a - 1], carrier),)))
            continue
        h = sp.Symbol(name, real=True)
        terms = []
        for i in range(n_obs):
            for k, expr in enumerate(ctx.feature_exprs):
                c = column.get(sp.expand(h * expr))
                if c is not None and (system.coef[i, c] != 0 or system.free[i, c]):
                    terms.append((ctx.observed_names[i], ctx.feature_names[k]))
        pivot = (ctx.observed_names[pivots[a][0]], ctx.feature_names[pivots[a][1]])
        terms = [pivot] + [t for t in terms if t != pivot]
        states.append(HiddenState(names[a], tuple(terms)))
    return tuple(states), rename


def terms_of(system, rename, names_map, stderr=None):
    """Term objects of every nonzero or estimated coefficient."""
    out = []
    free_index = {cell: k for k, cell in enumerate(zip(*np.nonzero(system.free), strict=True))}
    for r, state in enumerate(system.state_names):
        for c, feature in enumerate(system.features):
            value = float(system.coef[r, c])
            if value == 0 and not system.free[r, c]:
                continue
            k = free_index.get((r, c))
            se = float(stderr[k]) if stderr is not None and k is not None else math.nan
            out.append(Term(names_map.get(state, state), feature.xreplace(rename), value, se,
                            not bool(system.free[r, c])))
    return tuple(out)


def alternative(system, ctx, pivots, description, score, score_se, size, status, given,
                observed, nested=()):
    names = hidden_names(system, system.n_observed, given, observed)
    states, rename = describe(system, ctx, names, pivots, nested)
    names_map = dict(zip(system.state_names[system.n_observed:], names, strict=True))
    rhs = {}
    for t in terms_of(system, rename, names_map):
        rhs[t.state] = rhs.get(t.state, sp.Integer(0)) + sp.Float(t.value) * t.feature
    return Alternative(description, rhs, states, float(score), float(score_se), int(size),
                       status)


def _describe_origin(p):
    return f"{p.origin} ({p.n_states} hidden)"


# what the discovery's max_time leaves out when it is spent before the result is made
CHECKS = ("the checks that refit the chosen system (its simulated reference, terms beyond "
          "the search, the folded system, exchangeable, weakly supported and nearly "
          "needed terms)")


@timed("checks and result")
def from_verdicts(ordered, uncertain, ctx, coefs, given_names, unaided=None):
    """The result of a refined discovery: ``ordered`` verdicts, best first.
    ``unaided``: why stage one did not help (the law was found without it), or None;
    then the held-out check's reference is always simulated. A reference above
    ``checks.POWER`` is a doubt (``weak check``)."""
    best = ordered[0]
    system, fit, problem = best.system, best.fit, best.problem
    observed = list(ctx.observed_names)
    names = hidden_names(system, system.n_observed, given_names, observed)
    pivots = best.proposal.structure.pivots
    states, rename = describe(system, ctx, names, pivots, best.proposal.nested)
    names_map = dict(zip(system.state_names[system.n_observed:], names, strict=True))
    terms = terms_of(system, rename, names_map, fit.standard_errors())
    trajectories = problem.trajectories(fit)
    hidden = [tr[:, system.n_observed:] for tr in trajectories]
    stds = problem.state_std(fit)
    before = _nrmse(problem.trajectories_of(best_initial(best)), ctx.observed)
    after = _nrmse(trajectories, ctx.observed)
    refinement = Refinement(before, after, fit.gap, problem.n_segments, fit.iterations,
                            fit.status)

    def alt(v):
        return alternative(v.system, ctx, v.proposal.structure.pivots,
                           _describe_origin(v.proposal), v.cv, v.cv_se, v.size,
                           "scored" if v.scored else v.history[0], given_names, observed,
                           v.proposal.nested)

    alternatives = tuple(alt(v) for v in ordered[1:])
    unsure = tuple(alt(v) for v in uncertain)
    # an unscored winner (every candidate blew up or does not join) has no score
    score, score_se = (best.cv, best.cv_se) if best.scored else (math.inf, math.nan)
    notes = list(_static_notes(terms, names))
    # a score above ~1 is measured against what this system would score if it were
    # right (short segments: their starts' uncertainty is in the prediction too)
    simulate = (best.scored and np.isfinite(score)
                and bool(unaided or not reproduces(score, score_se)))
    # a fit whose segments do not meet is no trajectory of its system: refitting it with
    # other terms, or on data simulated from it, would measure its tearing (the
    # ``not continuous`` doubt says so; Hindmarsh-Rose at 1%: 20-40 s of such refits)
    # max_time spent: the checks are left out (and said to be), not run on refits cut
    # short after their first iteration, whose verdicts would not mean what they say
    expected, (extended, beyond), folded, exchangeable, weak, missing = (
        _refitting_checks(best, ctx, simulate) if fit.continuous and not spent(CHECKS)
        else (None, (None, []), None, [], [], []))
    if expected is not None:
        notes.append(f"a right system's held-out score at this sampling: {expected:.3g} "
                     "(simulated from the fitted system, its noise level and times)")
    unmeasured = left_out(CHECKS) or left_out(REFERENCE)  # max_time left the reference out
    part = judged_part(problem) if best.scored else None
    judged = problem if part is None else part  # what the score was taken on
    if part is not None:
        used, total = part.n_data // problem.n_obs, problem.n_data // problem.n_obs
        pieces = (f", cut into {len(part.groups)} pieces where the data are split"
                  if len(part.groups) > WINDOWS else "")
        notes.append(f"long recording ({total} samples): the terms were chosen, and the "
                     "held-out scores (this system's and the alternatives') taken, on "
                     f"{WINDOWS} windows of about {round(used / WINDOWS)} samples "
                     f"spread over it ({used} samples in all{pieces}); this system's "
                     "coefficients and their errors come from a fit to every sample (the "
                     "alternatives' from the windows)")
    result = HiddenDiscovery(
        ctx.times[0], ctx.observed[0], hidden[0], stds[0][:, system.n_observed:],
        tuple(observed), tuple(names), states, terms, coefs, score, score_se,
        alternatives, unsure, refinement, tuple(notes), list(ctx.times), list(ctx.observed),
        hidden, [np.asarray(h) for h in best.proposal.hidden], trajectories[0][0].copy(),
        doubts(score, score_se, refinement, terms, names,
               None if best.scored else best.history[0], expected, unmeasured)
        + weak_check_doubts(expected, unaided, best.scored and np.isfinite(score),
                            (len(judged.groups), score_se) if by_recording(judged)
                            else None, unmeasured)
        + segment_constant_doubts(terms, names, system.n_observed, trajectories, stds)
        + first_integral_doubt(best, names)
        + exchange_doubts(exchangeable, system, rename, names_map)
        + weak_doubts(weak, system, rename, names_map)
        + missing_doubts(missing, system, rename, names_map)
        + beyond_doubts(beyond, extended, rename, names_map)
        + folded_doubts(folded, score, score_se, best.size, names)
        + observed_function_doubts(system, names_map)
        + partial_shift_doubts(system, names_map)
        + redundant_state_doubts(best, names_map, trajectories)
        + unresolved_doubts(system, trajectories, ctx.times, names_map))
    free = free_run_doubt(result, trajectories) if best.scored else ()
    return dataclasses.replace(result, doubts=result.doubts + free) if free else result


def _refitting_checks(best, ctx, simulate):
    """The checks that refit the chosen system, side by side: the simulated reference
    (when ``simulate``), terms beyond the search, the folded system (nested only),
    exchangeable, weakly supported and nearly needed terms. Each reads the verdict and
    fits copies, none depends on another, so on a CPU a second core takes some of them
    (:func:`.._core.parallel.map_on`; the same values as one after the other). On a
    slow system they are most of a call's time (Hindmarsh-Rose: five fits of 20-30 s
    each)."""
    problem, fit = best.problem, best.fit
    checks = [
        (lambda: _reference(problem, fit) if simulate else None,
         2.0 * REPLICATES if simulate else 0.0),
        (lambda: beyond_terms(best, ctx.feature_exprs, ctx.free_rows), 1.5),
        (lambda: (folded_score(best, ctx.closure_library)
                  if best.proposal.nested else None), 1.0 if best.proposal.nested else 0.0),
        (lambda: exchangeable_terms(best), 1.0),
        (lambda: weakly_supported_terms(best), 1.0),
        (lambda: nearly_needed_terms(best), 1.0),
    ]
    return map_on(problem.options.device, lambda check: check[0](), checks,
                  cost=[c for _, c in checks])


def _reference(problem, fit):
    """:func:`.fit.expected_score.expected_score` of ``fit``, on the windows its score
    was taken on where the recording was judged on windows (:mod:`.fit.windows`), so
    that the reference is read against a score of the same kind."""
    part = judged_part(problem)
    if part is None:
        return expected_score(problem, fit)
    try:
        own = part.fit(fit.system, fit.starts[part.rows], penalties=(fit.rho,))
    except BlowUp:
        return None
    return expected_score(part, own)


def _static_notes(terms, names):
    """A hidden state whose equation is empty is a constant: say so."""
    moving = {t.state for t in terms if t.value != 0}
    return [f"{n} has no dynamics of its own (d{n}/dt = 0): it acts as a constant, so "
            "these data need no hidden variable there" for n in names if n not in moving]


def best_initial(verdict):
    """(system, starts) before refinement: the closure's coefficients, guessed starts."""
    return verdict.problem.system, verdict.problem.initial_starts


def from_proposals(proposals, ctx, coefs, given_names, stage_one_std):
    """The result without refinement: proposals ranked by their closure's held-out
    error, coefficients from the closure's integral fit."""
    ranked = sorted(proposals, key=lambda p: p.score)
    best = ranked[0]
    system, _, guesses = build(best, ctx)
    observed = list(ctx.observed_names)
    names = hidden_names(system, system.n_observed, given_names, observed)
    states, rename = describe(system, ctx, names, best.structure.pivots)
    names_map = dict(zip(system.state_names[system.n_observed:], names, strict=True))
    terms = terms_of(system, rename, names_map)
    hidden = [np.asarray(g)[:, system.n_observed:] for g in guesses]
    alternatives = []
    for p in ranked[1:]:
        sys_p = build(p, ctx)[0]
        alternatives.append(alternative(sys_p, ctx, p.structure.pivots, _describe_origin(p),
                                        math.nan, math.nan, sys_p.n_free, "not refined",
                                        given_names, observed))
    std = np.full(hidden[0].shape, np.nan)
    for a, pivot in enumerate(best.structure.pivots):
        if pivot in stage_one_std:
            std[:, a] = stage_one_std[pivot]
    return HiddenDiscovery(
        ctx.times[0], ctx.observed[0], hidden[0], std, tuple(observed), tuple(names), states,
        terms, coefs, math.nan, math.nan, tuple(alternatives), (), None, (),
        list(ctx.times), list(ctx.observed), hidden, [np.asarray(h) for h in best.hidden],
        np.asarray(guesses[0][0], dtype=float), (NOT_CHECKED,))


def _nrmse(trajectories, observed):
    """RMS over observed states of (model - data) / std(data), all trajectories."""
    model = np.vstack([tr[:, :observed[0].shape[1]] for tr in trajectories])
    data = np.vstack(observed)
    std = np.maximum(data.std(axis=0), 1e-300)
    return float(np.sqrt(np.nanmean(((model - data) / std) ** 2)))
