"""The winner restated: the same dynamics written another way, refined, its terms
selected and scored like any proposal, so that ranking can prefer the simpler form.

* :func:`shifted`: hidden states shifted to absorb the observed terms (:mod:`.gauge`);
* :func:`regauged`: the hidden state as the coefficient of another library term;
* :func:`integrated`: a hidden state and its rate as one state, where the rate's law
  has a first integral (:mod:`.first_integral`);
* :func:`nested_shifted`: a nested state shifted out of its flat direction
  (:mod:`.nested`);
* :func:`reduced`: a nested state that is a function of the observed states
  substituted out (:mod:`.observed_function`);
* :func:`function_reduced`: one of several hidden states that is an exact function of
  the other states substituted out (:func:`.observed_function.state_function`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import sympy as sp

from .._core.timing import timed
from .context import Context
from .fit.refine import Problem
from .fit.shooting import BlowUp
from .propose.nested import shifted_nested_system
from .propose.proposal import close
from .propose.smoother import HiddenFit, single_term
from .rewrite.first_integral import integrated_proposal, integrated_system
from .rewrite.gauge import shifted_guesses, shifted_proposal, shifted_system
from .rewrite.observed_function import function_reduced_system, reduced_proposal, reduced_system
from .verdict import Trial, Verdict, finish, first_fit, judged_on

# A winner's hidden state is restated as the coefficient of another term only where that
# term stays above this fraction of its RMS value on the winner's trajectories.
REGAUGE_FLOOR = 0.02


def shifted(verdict: Verdict, ctx: Context, options) -> Verdict | None:
    """The chosen system in the gauge that absorbs its observed terms into the hidden
    states (:mod:`.gauge`), refined, its terms selected and scored; None if there is
    none or it cannot be integrated."""
    found = shifted_system(verdict, ctx)
    if found is None or found[0] is None:
        return None
    system, shifts, dropped = found
    guesses = shifted_guesses(verdict.problem.trajectories(verdict.fit), verdict.system,
                              shifts)
    if guesses is None:
        return None
    proposal = shifted_proposal(verdict.proposal, dropped, guesses, system.n_observed)
    return restated(proposal, system, guesses, (ctx.times, ctx.observed), verdict, options)


@timed("restatements")
def regauged(verdict: Verdict, ctx: Context, options) -> Verdict | None:
    """The chosen hidden state restated as the coefficient of another library term of
    its equation, from the chosen system's own trajectories; refined, its terms selected
    and scored. None when the chosen system has not one first-order hidden state seen
    through one term, or no other term stays away from zero on its trajectories.

    A hidden state read off the data by the smoother is noisiest where its carrier is
    small: one epidemic wave seen through the infected at 5% noise gives h = (dI/dt) / I
    too rough to close, and the true structure (h the coefficient of I) is refined from
    a wrong closure and rejected, while ``dI/dt = h`` with a four-term law for h fits one
    wave to the noise and wins alone. The fitted system's trajectories are smooth and
    its rate exact, so ``h' = rate / theta`` (the new carrier ``theta``) is a clean series:
    its closure is fitted, and the carrier whose series closes best is refined (stopped
    early when hopeless) and, within twice the chosen one's misfit, its terms selected
    and scored; ranking decides (the smaller system within the band wins; an equal one
    makes the result uncertain)."""
    p = verdict.proposal
    if p.order != 1 or p.nested or p.structure.n_hidden != 1:
        return None
    (i, k), = p.structure.pivots
    if np.count_nonzero(p.structure.loadings) != 1 or not ctx.free_rows[i]:
        return None
    trajectories = verdict.problem.trajectories(verdict.fit)
    if not all(np.all(np.isfinite(tr)) for tr in trajectories):
        return None
    system = verdict.system
    n_obs = system.n_observed
    rate = sp.lambdify(system.symbols, system.rhs()[system.state_names[i]], modules="numpy")
    rates = [np.broadcast_to(rate(*tr.T), (len(tr),)) for tr in trajectories]
    others = p.structure.support.copy()
    others[i] = False
    best = None
    for j, expr in enumerate(ctx.feature_exprs):
        if j == k:
            continue
        carrier = sp.lambdify(system.symbols[:n_obs], expr, modules="numpy")
        thetas = [np.broadcast_to(carrier(*tr[:, :n_obs].T), (len(tr),)).astype(float)
                  for tr in trajectories]
        scale = np.sqrt(np.mean(np.concatenate(thetas) ** 2))
        if min(np.min(np.abs(th)) for th in thetas) < REGAUGE_FLOOR * scale:
            continue  # the carrier comes near zero: the restated state would blow up
        structure = single_term(n_obs, len(ctx.feature_exprs), i, j, others)
        fit = HiddenFit(structure, p.fit.constants, [(r / th)[:, None] for r, th in
                                                     zip(rates, thetas, strict=True)],
                        verdict.fit.residual_variance, 0.0)
        try:
            q = close(structure, fit, ctx, p.origin + f", restated as the coefficient of {expr}")
        except (np.linalg.LinAlgError, ValueError):
            continue
        if np.isfinite(q.score) and (best is None or q.score < best.score):
            best = q
    if best is None:
        return None
    misfit = verdict.fit.residual_variance
    trial = first_fit(best, ctx, options, misfit)
    if trial is None or trial.fit.residual_variance > 2.0 * max(misfit, 1.0):
        return None  # judged as the proposals are: beyond twice the best, not scored
    return finish(trial)


def nested_shifted(verdict: Verdict, ctx: Context, options) -> Verdict | None:
    """A nested winner with its nested state shifted out of its flat direction
    (:func:`.nested.shifted_nested_system`), refined, its terms selected and scored;
    None if there is no such shift or it cannot be integrated."""
    found = shifted_nested_system(verdict, ctx)
    if found is None:
        return None
    system, shifts = found
    guesses = shifted_guesses(verdict.problem.trajectories(verdict.fit), verdict.system,
                              shifts)
    if guesses is None:
        return None
    proposal = verdict.proposal.derived(", nested state shifted",
                                        hidden=[g[:, system.n_observed:] for g in guesses])
    data = (verdict.problem.times, verdict.problem.observed)
    return restated(proposal, system, guesses, data, verdict, options)


def reduced(verdict: Verdict, options) -> Verdict | None:
    """A nested winner without its nested state where that state is a function of the
    observed states (:mod:`.observed_function`), refined, its terms selected and
    scored; None if there is none or it cannot be integrated."""
    found = reduced_system(verdict)
    if found is None:
        return None
    system, guesses, candidates = found
    name = verdict.system.state_names[-1]
    proposal = reduced_proposal(verdict.proposal, guesses, system.n_observed, name)
    data = (verdict.problem.times, verdict.problem.observed)
    return restated(proposal, system, guesses, data, verdict, options, candidates)


def function_reduced(verdict: Verdict, options) -> Verdict | None:
    """A winner with several first-order hidden states (none nested) without the last
    one that is an exact function of the others, refined, its terms selected and
    scored; None if there is none or it cannot be integrated."""
    p, system = verdict.proposal, verdict.system
    if p.nested or p.order != 1 or p.structure.n_hidden < 2:
        return None
    n_obs = system.n_observed
    for state in reversed(range(n_obs, len(system.state_names))):
        found = function_reduced_system(verdict, state)
        if found is None:
            continue
        reduced_sys, guesses, candidates = found
        a = state - n_obs
        st = p.structure
        structure = replace(st, loadings=np.delete(st.loadings, a, axis=-1),
                            pivots=st.pivots[:a] + st.pivots[a + 1:])
        proposal = p.derived(f", {system.state_names[state]} as a function of the other "
                             "states", structure=structure, hidden=[g[:, n_obs:] for g in guesses])
        data = (verdict.problem.times, verdict.problem.observed)
        return restated(proposal, reduced_sys, guesses, data, verdict, options, candidates)
    return None


def integrated(verdict: Verdict, options) -> Verdict | None:
    """The chosen hidden state and rate as one hidden state, where the rate's law is the
    derivative of a first-order law (:mod:`.first_integral`), refined, its terms
    selected and scored; None if there is none or it cannot be integrated."""
    found = integrated_system(verdict)
    if found is None:
        return None
    system, guesses = found
    proposal = integrated_proposal(verdict.proposal, guesses, system.n_observed)
    data = (verdict.problem.times, verdict.problem.observed)
    return restated(proposal, system, guesses, data, verdict, options)


@timed("restatements")
def restated(proposal, system, guesses, data, verdict, options,
              candidates=None) -> Verdict | None:
    """``verdict``'s system restated as ``system`` (from ``guesses``), refined, its terms
    selected (``candidates``: terms it may add; none by default) and scored on ``data``
    (times, observed); None if it cannot be integrated."""
    if candidates is None:
        candidates = np.zeros_like(system.free)
    try:
        problem, whole = judged_on(Problem(system, *data, guesses, options))
        trial = Trial(proposal, problem, problem.fit(system), candidates,
                      verdict.initial_misfit, whole)
    except BlowUp:
        return None
    return finish(trial)

