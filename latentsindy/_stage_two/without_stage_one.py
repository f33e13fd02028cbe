"""Laws found where stage one sees none: sparse samples and panels of short recordings.

Stage one reads a law from derivatives. Sampled a few times per cycle, its
differentiator's window spans the cycle and no term survives; in a panel of short
recordings (subjects, batches, trials: 8-15 samples each) there is not even one
recording long enough for it. The data may still plainly move. Then stage two looks
for the law itself: every library term of every free equation is proposed as the
carrier of one hidden state, its hidden series fitted in integral form on the samples
as measured (no derivative), and the judge refines, selects terms and scores them like
any proposal (all recordings share the law, each with its own hidden start). The
result's notes say so; it carries the ``without stage one`` doubt when the law it found
keeps every closure term (:func:`saturated`: no sparse law, the sign of a wrong
carrier's approximation), and the ``weak check`` doubt when the held-out check has
little power on such data (a right system's simulated score above 3 noise variances,
or not measurable: :func:`.doubts.checks.weak_check_doubts`).

The same carriers are judged where stage one saw a law with no coefficient varying
and that law, judged alone, misses held-out data (:func:`reproduced`).
"""

from __future__ import annotations

import numpy as np
import sympy as sp

from .._core.doubt import Doubt
from .._core.library import feature_expressions
from .._core.threads import single_thread
from .._stage_one.coefficients import CoefficientSeries
from . import context_build
from .doubts.checks import REPRODUCTION_SLACK
from .fit.refine import RefineOptions
from .propose.hypotheses import every_carrier
from .propose.proposal import without_hidden
from .verdict import closure_state_names, first_fit

# Misfit (noise variances per sample, integrated against the data) of the law without
# hidden states (stage one's terms as constants; none: the states held constant) above
# which the observed states do not close on their own (a right law: about 1; with 2% of
# the samples hit by spikes of 10 noise levels, 3). Where no coefficient varied, stage
# two then judges every library term as a hidden carrier.
MOVES = 4.0


def misfit(proposal, ctx, refine, device) -> float:
    """Misfit of ``proposal`` in noise variances per sample: of its system integrated
    against the data (``refine``; inf when it blows up), else of the smoother's
    integral-form fit (short anchored stretches, which a wrong law can still follow)."""
    if not refine:
        return proposal.fit.misfit
    with single_thread():
        trial = first_fit(proposal, ctx, RefineOptions(device=device))
    return np.inf if trial is None else trial.fit.residual_variance


# The step :func:`reproduced` adds, as ``max_time`` names it when it is left out.
BESIDE = "hidden carriers beside the law without hidden states"


def with_carriers(ctx, proposals, support, library, panel, fuller):
    """(context, proposals, blind): ``proposals`` (the law without hidden states first)
    with every library term as a hidden carrier (:func:`carriers`), the context they
    are judged in, and whether stage one saw no law where the data move
    (:func:`no_terms`: outside a panel the context is then the data as measured, and
    the law without hidden states is fitted again there)."""
    blind = no_terms(support, ctx)
    if blind and not panel:
        ctx = context_build.as_measured(ctx, library)
        proposals = [without_hidden(support, ctx)]
    return ctx, [proposals[0]] + carriers(ctx, support, fuller=fuller), blind


def reproduced(ordered) -> bool:
    """Whether the law without hidden states, judged alone, reproduces held-out data
    down to their noise: scored at most ``1 + REPRODUCTION_SLACK`` noise variances.

    That law is judged alone when its integrated misfit is below ``MOVES`` (short
    anchored segments, which a wrong law can follow); its held-out score is the better
    test, and it is read as it stands, not within two standard errors: a wrong law
    misses some stretches by far and others not at all, so its standard error is wide
    (Lorenz seen through x and z at 5% noise, one wing, draw 9: a two-state law of x and
    z at 1.45 +- 0.46, where a right system's standard error here is about 0.025; two
    competing species seen through x, a logistic law at 1.27 +- 0.06), and the doubt's
    two-standard-error test passed both with confidence. Above it (or unscored) the
    carriers are judged beside it and ranked with it as any hypotheses are: it wins
    where the held-out data do not reject it (it is the smallest), and is then
    reported as before (confident when its checks pass); carriers that the paired
    errors favour make it uncertain. A right law scoring above 1.15 (short or sparse
    recordings, where a right system's reference is 1-2.3) pays the carriers' time."""
    return bool(ordered and ordered[0].scored
                and ordered[0].cv <= 1.0 + REPRODUCTION_SLACK)


def no_terms(support, ctx) -> bool:
    """Whether stage one kept no term in some free equation (asked where the data
    move: its differentiator could not see a law, sampled a few times per cycle, its
    window spanning the cycle)."""
    empty = ~np.asarray(support, bool).any(axis=1) & np.asarray(ctx.free_rows, bool)
    return bool(empty.any())


def note(panel: bool) -> str:
    """What a law found on this path rests on (a note: on its own no reason for doubt;
    the held-out score, against what a right system would score at this sampling, is
    the check)."""
    return (f"{_why(panel)}, so this law was found without it: the search started from "
            "laws with one hidden state carried by one library term, their hidden series "
            "fitted in integral form")


def saturated(verdict) -> list[int]:
    """Hidden states (indices) whose law keeps every term of the closure library.

    Without stage one every library term is tried as the carrier; a wrong carrier's
    law can still reproduce the data when it keeps every term it may (a generic
    polynomial, no sparse law: prey-only Lotka-Volterra at 8 samples per cycle and in
    a panel of 20 x 11 samples, ``dx/dt = h x^2`` with all six terms of degree 2
    scored at or below the exact law). The exact laws of every benchmark family
    leave terms out."""
    system, p = verdict.system, verdict.proposal
    if not len(p.closure.coef):
        return []
    names = list(system.state_names)
    states = closure_state_names(p, names[:system.n_observed], names[system.n_observed:])
    n_in = getattr(p.closure.library, "n_features_in_", len(states))
    if getattr(p, "nested", None) or n_in != len(states):
        return []  # a nested state's law is closed in other states: not this check's
    features = [sp.expand(f) for f in system.features]
    exprs = [sp.expand(e) for e in feature_expressions(
        p.closure.library, list(p.closure.feature_names), states)]
    cols = [features.index(e) for e in exprs if e in features]
    if len(cols) < len(exprs):  # restated in other features: not this closure's law
        return []
    closed = [len(names) - 1] if p.order == 2 else range(system.n_observed, len(names))
    return [r - system.n_observed for r in closed
            if system.free[r].any() and np.all(system.coef[r, cols] != 0)]


def carriers(ctx, support, fuller=True) -> list:
    """Every library term of every free equation as the carrier of one hidden state
    (:func:`.propose.hypotheses.every_carrier`), the other equations with their own
    laws (:func:`own_laws`): the criterion's, and where it differs, the sparsest (one
    term each) too. On 11 irregular samples a cycle the trapezoid's error buys the
    criterion's law a curvature term or two (the oscillator's ``dx/dt = A y`` came
    with ``x^2`` and ``y^2``), and a right carrier's system with them could not be
    fitted at all (the oscillator's 20 x 11 panels, draws 2 and 4); term selection
    takes terms out, but only of a system that was fitted."""
    laws = own_laws(ctx, support)
    out = every_carrier(ctx, support, fuller=fuller, others=laws)
    if support.shape[0] < 2:  # no other equation: the laws change nothing
        return out
    sparsest = own_laws(ctx, support, max_terms=1)
    if not np.array_equal(sparsest, laws):
        seen = {(p.structure.key(), p.order) for p in out}
        for p in every_carrier(ctx, support, fuller=fuller, others=sparsest):
            if (p.structure.key(), p.order) not in seen:
                seen.add((p.structure.key(), p.order))
                out.append(p)
    return out


def own_laws(ctx, support, max_terms=None) -> np.ndarray:
    """The support, with every free equation that has no term given the sparse law with
    constant coefficients that its increments call for: forward selection on the
    integral form (each increment between neighbouring samples against the trapezoid
    integral of every library term, pooled over the recordings) while the extended
    BIC falls (a term costs log n + log F, the residual variance unknown).

    Without stage one every library term of an equation is tried as a hidden carrier;
    the other equations need laws of their own, or the carrier's system cannot move the
    other states. Stage one gives them where it ran; in a panel of short recordings it
    gives none, and a right carrier then started with its neighbour's law empty (the
    oscillator's 20 x 11 panels, ``dy/dt = B(t) x`` with ``dx/dt = A y``: 0 exact of
    10, each a wrong law, flagged). An equation that needs a hidden state of its own
    gets an approximation here, which matters only for the carriers of other
    equations; its own carriers start bare, as before."""
    out = np.array(support, dtype=bool, copy=True)
    rows = [i for i in range(out.shape[0]) if ctx.free_rows[i] and not out[i].any()]
    if not rows:
        return out
    design, increments = [], []
    for x, t, th in zip(ctx.observed, ctx.times, ctx.thetas, strict=True):
        if len(t) < 2:
            continue
        step = np.diff(np.asarray(t, float))[:, None]
        design.append(0.5 * (th[:-1] + th[1:]) * step)
        increments.append(np.diff(np.asarray(x, float), axis=0))
    if not design:
        return out
    a, b = np.vstack(design), np.vstack(increments)
    ok = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    a, b = a[ok], b[ok]
    n, n_feat = a.shape
    if n <= n_feat:
        return out
    price = np.log(n) + np.log(n_feat)
    for i in rows:
        out[i] = _forward(a, b[:, i], price, max_terms)
    return out


def _forward(a, y, price, max_terms=None) -> np.ndarray:
    """Terms chosen by forward selection while ``n log(rss / n) + price k`` falls."""
    n = len(y)
    chosen: list[int] = []
    best = n * np.log(max(float(y @ y) / n, 1e-300))
    while len(chosen) < (max_terms or a.shape[1]):
        trials = []
        for f in range(a.shape[1]):
            if f in chosen:
                continue
            cols = a[:, chosen + [f]]
            coef = np.linalg.lstsq(cols, y, rcond=None)[0]
            rss = float(np.sum((y - cols @ coef) ** 2))
            trials.append((n * np.log(max(rss / n, 1e-300)) + price * (len(chosen) + 1), f))
        crit, f = min(trials)
        if crit >= best:
            break
        best = crit
        chosen.append(f)
    mask = np.zeros(a.shape[1], dtype=bool)
    mask[chosen] = True
    return mask


def doubt(panel: bool, hidden: list[str]) -> Doubt:
    which = ", ".join(f"d{h}/dt" for h in hidden)
    return Doubt("without stage one", f"{which} keeps every term of the closure library: "
                 f"a generic polynomial, not a sparse law. {note(panel)[0].upper()}"
                 f"{note(panel)[1:]}, and a wrong carrier's law can fit this way. Confirm "
                 "it with denser samples or more recordings.")


def _why(panel: bool) -> str:
    return ("no recording is long enough for stage one (16 samples between gaps)"
            if panel else "stage one kept no term although the data move (too few "
            "samples per cycle, so that its differentiator's window spans much of one; or "
            "spikes left in the data, as with outliers=\"keep\")")


def stand_in(trajs, times, names, features, library, differentiation_method):
    """What stage one would have given, for a panel it cannot read: a fitted library
    (and the differentiator) for stage two's context, and coefficients that are all
    zero with no term kept (the result's ``coefficients`` then say so)."""
    library.fit([np.asarray(x) for x in trajs])
    model = _StandIn(library, differentiation_method)
    n_obs, n_feat = len(names), len(features)
    t = np.asarray(times[0], float)
    zeros = np.zeros((len(t), n_obs, n_feat))
    none = np.zeros((n_obs, n_feat), dtype=bool)
    coefs = CoefficientSeries(
        t, zeros, zeros.copy(), zeros[None].copy(), tuple(names), tuple(features), none,
        none.copy(), np.zeros((n_obs, n_feat)), np.zeros((n_obs, n_feat)), zeros.copy(),
        zeros.copy(), (Doubt("no law", "not estimated: every recording is shorter than "
                             "stage one needs (16 samples); stage two searched alone"),))
    return model, coefs


class _StandIn:
    """The two attributes of a fitted stage one that stage two's context reads."""

    def __init__(self, library, differentiation_method):
        self.library_ = library
        self.differentiation_method = differentiation_method
