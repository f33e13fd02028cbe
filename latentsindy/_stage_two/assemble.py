"""From judged proposals to a :class:`HiddenDiscovery` (names, terms, series, alternatives)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import sympy as sp
from scipy.integrate import solve_ivp

from .._core.timing import timed
from .first_integral import integrated_system
from .judge import build, exchangeable_terms, weakly_supported_terms
from .nested import monomial_name
from .result import Alternative, HiddenDiscovery, HiddenState, Refinement, Term

# A closed system reproduces held-out data when its score (held-out misfit in noise
# variances) is ~1. The noise level is itself estimated from the data (to ~10%), so a
# score is called too high only when it exceeds 1 + REPRODUCTION_SLACK by two standard
# errors. Over the discovery benchmark's correct results the largest
# score - 2 se was 1.07; a missing term or hidden state gives more.
REPRODUCTION_SLACK = 0.15
SIGNIFICANCE = 2.0  # a kept coefficient should be this many standard errors from zero
NOT_CHECKED = ("not refined by integration (refine=False): the structure was chosen by its "
               "closure's held-out error and was never checked by integrating it against "
               "the data")


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
    map of symbols. ``nested``: :attr:`.hypotheses.Proposal.nested`, the hidden states
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


@timed("checks and result")
def from_verdicts(ordered, uncertain, ctx, coefs, given_names):
    """The result of a refined discovery: ``ordered`` verdicts, best first."""
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
    notes = _static_notes(terms, names)
    result = HiddenDiscovery(
        ctx.times[0], ctx.observed[0], hidden[0], stds[0][:, system.n_observed:],
        tuple(observed), tuple(names), states, terms, coefs, score, score_se,
        alternatives, unsure, refinement, tuple(notes), list(ctx.times), list(ctx.observed),
        hidden, [np.asarray(h) for h in best.proposal.hidden], trajectories[0][0].copy(),
        doubts(score, score_se, refinement, terms, names)
        + _segment_constants(terms, names, system.n_observed, trajectories, stds)
        + _first_integral(best, names)
        + _exchanges(exchangeable_terms(best), system, rename, names_map)
        + _weak(weakly_supported_terms(best), system, rename, names_map))
    free = _free_run(result, trajectories) if best.scored else ()
    return dataclasses.replace(result, doubts=result.doubts + free) if free else result


FREE_RUN_RTOL = 1e-4  # a blow-up check, not a fit: a loose tolerance suffices
FREE_RUN_BUDGET = 60_000  # right-hand-side evaluations per recording


def _free_run(result, trajectories):
    """A doubt when the closed system, integrated over a whole recording from its fitted
    initial state, blows up or exhausts its step budget.

    The refinement fits and the judge scores the system segment by segment (multiple
    shooting), so a wrong law that follows the data over short stretches can fit and
    score as well as the truth; over the whole recording it need not stay near the
    data at all. A law that reproduces a recording keeps a bounded trajectory over it
    (chaos may take it elsewhere on the attractor, not to infinity), so a blow-up
    (any state beyond 1000 times the largest fitted magnitude) is a failed check (a
    non-spiking Rossler with z hidden at 1% noise: a six-term hidden law fitted the
    segments to their noise, confidently, and blew up within the recording). LSODA
    (stiffness detected, so a stiff law is not mistaken for an unstable one), about
    0.1-0.2 s per recording of 2000 samples.
    """
    field = result.vector_field()
    for k, (t, states) in enumerate(zip(result.all_times, trajectories, strict=True)):
        status = _bounded_run(field, t, states)
        if status == "success":
            continue
        where = f"recording segment {k}" if len(trajectories) > 1 else "the recording"
        what = {"blow_up": "blows up",
                "step_budget": "exhausts its step budget (stiff or nearly singular)"}.get(
                    status, "could not be integrated (the solver failed)")
        return (f"integrated over {where} from its fitted initial state (not segment by "
                f"segment, as it was fitted and scored), the closed system {what}: it "
                "follows the data over short stretches only, which a wrong law can do; more "
                "data, less noise or another closure_library may settle it",)
    return ()


class _Budget(Exception):
    pass


def _bounded_run(field, t, states):
    """"success", "blow_up" (a state beyond 1000 times the fitted states' largest
    magnitude, or not finite), "step_budget" or "failed" for a run over ``t`` from
    ``states[0]``."""
    scale = max(1.0, float(np.nanmax(np.abs(states))))
    count = [0]

    def rhs(ti, y):
        count[0] += 1
        if count[0] > FREE_RUN_BUDGET:
            raise _Budget
        return np.asarray(field(ti, y), dtype=float)

    def escaped(ti, y):
        return 1e3 * scale - float(np.max(np.abs(y)))

    escaped.terminal = True
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            sol = solve_ivp(rhs, (float(t[0]), float(t[-1])), np.asarray(states[0], float),
                            method="LSODA", rtol=FREE_RUN_RTOL,
                            atol=FREE_RUN_RTOL * 1e-3 * scale, events=escaped)
    except _Budget:
        return "step_budget"
    if sol.status == 1 or not np.all(np.isfinite(sol.y)):
        return "blow_up"
    return "success" if sol.success else "failed"


def _term_text(cell, system, rename, names_map):
    r, c = cell
    state = system.state_names[r]
    return f"{system.features[c].xreplace(rename)} in d{names_map.get(state, state)}/dt"


def _weak(found, system, rename, names_map):
    """A sentence per term the data support only weakly, or whose support could not be
    checked."""
    out = []
    for cell, change, bar in found:
        if cell is None:
            out.append("the support of the terms could not be checked (refitting without "
                       "a term blew up): they may include terms the data do not need")
        elif not np.isfinite(change):
            out.append(f"the support of {_term_text(cell, system, rename, names_map)} could "
                       "not be checked (refitting without it failed): it may stand for a "
                       "small systematic error rather than part of the law")
        else:
            out.append(
                f"the data support {_term_text(cell, system, rename, names_map)} only weakly "
                f"(dropping it raises the misfit by {change:.3g} residual variances, under "
                f"the {bar:.3g} that very strong evidence needs): it may stand for a small "
                "systematic error rather than part of the law")
    return tuple(out)


def _exchanges(moves, system, rename, names_map):
    """A sentence per term exchange the data do not refuse."""
    def term(cell):
        return _term_text(cell, system, rename, names_map)

    out = []
    for (kind, (gone, new)), change in moves:
        gone = " and ".join(term(g) for g in gone) if kind != "swap" else term(gone)
        new = " and ".join(term(g) for g in new) if kind == "exchange" else term(new)
        what = ("a smaller system fits almost as well" if kind == "merge"
                else "an equally good system")
        out.append(f"the data cannot tell {gone} from {new} (exchanging them changes the "
                   f"misfit by {change:+.2g} residual variances): {what}")
    return tuple(out)


def doubts(score, score_se, refinement, terms, hidden):
    """The checks a refined system fails, each as a sentence with its remedy."""
    found = []
    if not (np.isfinite(score) and np.isfinite(score_se)):
        found.append("the closed system could not be scored on held-out data (its "
                     "integration blew up, or its hidden states jump between integration "
                     "segments): it was not checked against the data")
    elif score - SIGNIFICANCE * score_se > 1 + REPRODUCTION_SLACK:
        found.append(
            f"the closed system does not reproduce held-out data down to their noise (score "
            f"{score:.3g} +- {score_se:.2g}, expected ~1): a term or a hidden state is "
            "probably missing; try a richer library or closure_library, or more data")
    if refinement.status != "converged":
        found.append(
            f"refinement by integration stopped at its iteration limit ({refinement.status}, "
            f"{refinement.iterations} iterations): the coefficients are not a converged fit")
    weak = [f"d{t.state}/dt: {t.feature}" for t in terms
            if t.state in hidden and not t.fixed and np.isfinite(t.stderr)
            and abs(t.value) < SIGNIFICANCE * t.stderr]
    if weak:
        found.append(
            f"{len(weak)} hidden-equation coefficient(s) within {SIGNIFICANCE:g} standard "
            f"errors of zero ({', '.join(weak[:4])}{', ...' if len(weak) > 4 else ''}): "
            "the data do not determine them")
    return tuple(found)


def _segment_constants(terms, names, n_observed, trajectories, stds):
    """A hidden state without dynamics (``dh/dt = 0``) is one constant per recording (or
    gap-separated segment): when those constants differ beyond their standard errors,
    the recordings do not share one law (each gets its own parameter). A doubt per such
    state; also one when a constant cannot be read (a trajectory blew up)."""
    if len(trajectories) < 2:
        return ()
    moving = {t.state for t in terms if t.value != 0}
    found = []
    for a, name in enumerate(names):
        if name in moving:
            continue
        col = n_observed + a
        values = np.array([tr[0, col] for tr in trajectories])
        if not np.all(np.isfinite(values)):
            found.append(
                f"{name} has no dynamics of its own and its constant could not be read in "
                "every recording (an integration blew up): whether the recordings share "
                "one law was not checked")
            continue
        errors = np.array([sd[0, col] for sd in stds])
        spread = np.abs(values[:, None] - values[None, :])
        bound = SIGNIFICANCE * np.sqrt(errors[:, None] ** 2 + errors[None, :] ** 2)
        if np.any(spread > np.where(np.isfinite(bound), bound, 0.0)
                  + 1e-9 * np.max(np.abs(values))):
            found.append(
                f"{name} has no dynamics of its own but takes different constant values in "
                f"different recordings or segments ({', '.join(f'{v:.4g}' for v in values[:5])}"
                f"{', ...' if len(values) > 5 else ''}): they do not share one law (each "
                "has its own parameter); the system may describe each recording's trend "
                "rather than the dynamics. Longer recordings, or a hidden state with an "
                "equation of its own, are needed")
    return tuple(found)


def _first_integral(verdict, names):
    """A doubt when the winner's rate law has a first integral (:mod:`.first_integral`):
    the smaller first-order system with one constant was judged and not preferred, so
    the conserved quantity differs between recordings or segments, or the fit is not
    settled; either way the second hidden state is not shown to be dynamics."""
    if integrated_system(verdict) is None:
        return ()
    h, r = names[0], names[1]
    return (f"d{r}/dt is the time derivative of a first-order law for {h} "
            f"(d{h}/dt = G({h}) + c, with c = {r} - G({h}) conserved), yet that smaller "
            "system was not preferred: c differs between recordings or segments, or the "
            f"fit is not settled; {r} may stand for a constant per recording rather than "
            "dynamics",)


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
