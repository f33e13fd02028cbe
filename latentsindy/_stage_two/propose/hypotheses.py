"""Structures that could explain the data: proposals from stage one and alternatives.

Any state dependence can hide in a time-varying coefficient, so several structures
(which terms an observed equation has, which of them vary, and whether varying
coefficients share one hidden state) explain the derivatives about equally well. They
differ in what matters: whether the hidden series they imply close into a short
autonomous equation. Each proposal here gets its hidden series from the structured
smoother (:mod:`.smoother`) and a cheap closure (:mod:`.closure`);
its held-out closure error ranks it. The best few go on to the closed-loop judge
(:mod:`.judge`), which decides by integration.

Sources of proposals:

* stage one's varying coefficients, with the variation shared among them at each rank
  (coefficient series that are affine images of one another are one hidden state);
* for every equation whose coefficients vary, each library term as the one carrier of
  the variation (stage one may make the wrong term vary, or prune a real constant term
  whose role the variation took over); constant terms are then added or dropped one at
  a time while that improves the closure;
* stage one's carrier of each varying equation with every library term of that
  equation back as a constant, the small ones pruned by the smoother (
  :func:`with_every_constant`): stage one's varying coefficient can take in several
  state-dependent terms at once (a hidden drive's coefficient taking in a damped
  oscillator's restoring and friction terms), which adding one constant at a time
  cannot undo, since no single one of them makes the rest close;
* where several equations vary, one hidden state shared by the best carriers of each,
  and by every pair of carriers of two equations (:func:`.shared.carrier_pairs`): the best
  carrier of an equation on its own need not be the one it shares with another.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import sympy as sp

from ..._core.budget import spent
from ..._core.timing import timed
from ..context import Context
from .proposal import Proposal, close, evaluate
from .shared import across_equations, carrier_pairs, shared_variation
from .smoother import Structure, fit_hidden, prune_constants, single_term

MAX_RANK = 3  # at most this many hidden states from shared variation
KEEP = 3  # proposals passed on to the judge besides the ones always judged
IMPROVE = 0.8  # a constant-term move must cut the closure error by 20%
# what the discovery's max_time leaves out when it runs out while proposals are made:
# stage one's own structure is always evaluated, the alternatives as long as time is left
CUT = "alternative proposals (other carriers, constants moved, shared hidden states)"


@timed("proposals")
def propose(ctx: Context, support, varying_pairs, series, fuller=True, max_rank=MAX_RANK):
    """Ranked proposals (best first) for the judge.

    Parameters
    ----------
    support : bool (n_observed, n_features), stage one's terms
    varying_pairs : list of (equation, feature) indices, stage one's varying terms,
        most significant first
    series : (T, len(varying_pairs)) their posterior-mean series (first trajectory)
    fuller : bool
        Also the always-judged proposals with their closure's least-error support
        (:func:`fuller_closure`): a start for the integrated judge, whose term selection
        prunes. Without refinement (proposals ranked by closure error alone) they would
        win by construction, so leave them out there.
    max_rank : int
        At most this many hidden states from shared variation.

    Where the discovery's ``max_time`` runs out, the alternatives not yet evaluated are
    left out (stage one's own structure at rank one always is evaluated).
    """
    n_obs, n_feat = support.shape
    proposals = {}

    def add(p):
        key = (p.structure.key(), p.order)
        if key not in proposals or p.score < proposals[key].score:
            proposals[key] = p

    first = []  # always judged: stage one's own structure, and per equation the carrier
    # whose series fits the data best and the one whose series closes best
    for structure in shared_variation(support, varying_pairs, series, max_rank):
        if first and spent(CUT):
            break
        p = replace(evaluate(structure, ctx, "stage one"), stage_one=True)
        first.append(p) if not first else None
        add(p)
        add(improve_constants(p, ctx))
    reduced = {}  # gauge_reduced, once per structure

    def in_reduced_gauge(p):
        key = (p.structure.key(), p.order)
        if key not in reduced:
            if spent(CUT):
                return None
            reduced[key] = gauge_reduced(p, ctx)
        return reduced[key]

    equations = sorted({i for i, _ in varying_pairs})
    for i in equations:
        if spent(CUT):
            break
        k = next(k for j, k in varying_pairs if j == i)
        p = with_every_constant(ctx, support, i, k)
        if p is not None:
            add(p)
            first.append(p)
    best_carrier, every_carrier = {}, {}
    for i in equations:
        if not ctx.free_rows[i] or spent(CUT):
            continue
        # the other equations keep stage one's terms as constants
        carriers = _carriers(ctx, support, i, support)
        every_carrier[i] = carriers
        trials = _usable(carriers)
        fitting = min(trials, key=lambda p: p.fit.misfit)
        for p in [trials[0], fitting] + trials[1:2]:
            add(p)
            add(improve_constants(p, ctx))
        first += [trials[0], fitting]
        best_carrier[i] = trials[0]
        # every carrier also in its reduced gauge, ranked apart (ranked together, they
        # would displace carriers that close well as they are): the best-closing and
        # the best-fitting one are judged, the others compete for the remaining places
        gauged = _usable([q for q in map(in_reduced_gauge, carriers) if q is not None])
        for q in gauged:
            add(q)
        if gauged:
            first += [gauged[0], min(gauged, key=lambda q: q.fit.misfit)]
    # the always-judged structures also in the gauge where the hidden state carries its
    # equation's terms that are its carrier times observed states (see gauge_reduced)
    for p in list(first):
        q = in_reduced_gauge(p)
        if q is not None:
            add(q)
            first.append(q)
    if len(best_carrier) > 1:  # variation in several equations: one hidden or several
        for structure in across_equations(best_carrier, support):
            if structure.n_hidden > max_rank or spent(CUT):
                continue
            p = evaluate(structure, ctx, "shared")
            add(p)
            add(improve_constants(p, ctx))
        for structure in carrier_pairs(every_carrier, support):
            if spent(CUT):
                break
            add(evaluate(structure, ctx, "shared, a carrier pair"))
    chosen = []
    for p in first + _usable(list(proposals.values())):
        if all(p.structure.key() != q.structure.key() or p.order != q.order for q in chosen):
            chosen.append(p)
        if len(chosen) >= len(first) + KEEP:
            break
    # the always-judged structures also with the closure support of least held-out
    # error where the one-standard-error rule chose a sparser one: on short or noisy
    # records that rule can drop terms the law needs, and a closure without them cannot
    # be refitted back (the judge's term selection then prunes what is not needed)
    if not fuller:
        return chosen
    # (one per system: two always-judged proposals with the same structure, such as
    # stage one's and the best carrier's, give the same fuller closure)
    extra = {}
    for p in first:
        q = fuller_closure(p)
        if q is not None:
            extra.setdefault((q.structure.key(), q.order, q.closure.coef.tobytes()), q)
    return chosen + list(extra.values())


def every_carrier(ctx: Context, support, fuller=True, others=None) -> list[Proposal]:
    """Proposals without stage one's variation: in every free equation, each library
    term as the carrier of one hidden state (the equation's other terms as in
    ``support``), the hidden series from the smoother in integral form (no derivative
    of the data). For data sampled too sparsely for stage one's differentiator (a few
    samples per cycle: its window spans the cycle and no term survives), where the
    observed states plainly move. Per equation the best-closing and the best-fitting
    carrier, each also with constants moved and in its reduced gauge, then every other
    carrier that fits the data (within twice the best misfit; the integral-form
    closure score on a few samples per recording ranks them only roughly: in a panel
    of 20 x 11 prey-only LV samples ``x^2`` ranked above the exact carrier ``x``, and
    its system could not be integrated), and (``fuller``) each with its fuller
    closure. ``others`` (like ``support``): the terms of the equations other than the
    carrier's (default ``support``). Where the discovery's ``max_time`` runs out, the
    carriers not yet evaluated are left out (at least one is)."""
    n_obs, n_feat = support.shape
    chosen = {}
    for i in range(n_obs):
        if not ctx.free_rows[i] or (chosen and spent(CUT)):
            continue
        rest = np.array(support if others is None else others, dtype=bool, copy=True)
        rest[i] = support[i]
        carriers = _usable(_carriers(ctx, support, i, rest, needed=not chosen))
        if not carriers:
            continue
        picks = [carriers[0], min(carriers, key=lambda q: q.fit.misfit)]
        picks += [q for q in (gauge_reduced(p, ctx) for p in picks) if q is not None]
        for p in picks + [improve_constants(p, ctx) for p in picks] + carriers[1:]:
            chosen.setdefault((p.structure.key(), p.order), p)
    out = list(chosen.values())
    if fuller:
        out += [q for q in map(fuller_closure, out) if q is not None]
    return out


def _carriers(ctx: Context, support, equation: int, rest, needed=True) -> list[Proposal]:
    """Each library term as the one carrier of a hidden state in ``equation`` (the
    other equations' terms as in ``rest``), in turn, until the discovery's ``max_time``
    runs out (the first one regardless where ``needed``)."""
    n_obs, n_feat = support.shape
    carriers = []
    for k in range(n_feat):
        if (carriers or not needed) and spent(CUT):
            break
        carriers.append(evaluate(single_term(n_obs, n_feat, equation, k, rest), ctx,
                                 "carrier"))
    return carriers


def with_every_constant(ctx: Context, support, equation: int, carrier: int) -> Proposal | None:
    """One hidden state, the coefficient of ``carrier`` in ``equation``, with every
    other library term of that equation as a constant; the terms explaining less than
    the threshold of the equation's rate pruned (STLSQ with the smoother inside). The
    smoother's roughness penalty decides what is state-dependent (a constant times a
    library term) and what is the hidden state's own, slower variation. None for a fixed
    equation or when the fit fails."""
    if not ctx.free_rows[equation]:
        return None
    sup = np.array(support, dtype=bool, copy=True)
    sup[equation, :] = True
    return pruned(single_term(*sup.shape, equation, carrier, sup), ctx,
                  "carrier with every term, pruned")


def pruned(structure, ctx: Context, origin: str) -> Proposal | None:
    """``structure`` fitted by the smoother, its constant terms that explain less than
    the threshold of their equation's rate pruned (STLSQ with the smoother inside), and
    closed; None when a fit fails or is not finite."""
    try:
        fit = fit_hidden(structure, ctx.thetas, ctx.observed, ctx.times, ctx.sigma,
                         ctx.spacing)
        fit = prune_constants(fit, ctx.thetas, ctx.observed, ctx.times, ctx.sigma,
                              ctx.spacing, ctx.threshold, ctx.free_rows)
        p = close(fit.structure, fit, ctx, origin)
    except (np.linalg.LinAlgError, ValueError):
        return None
    return p if np.isfinite(p.score) and np.isfinite(p.fit.misfit) else None


def fuller_closure(p: Proposal) -> Proposal | None:
    """``p`` with its closure's least-error support (:class:`.closure.ClosureFit`'s
    ``fuller``); None when the chosen support is that one."""
    c = p.closure
    if c.fuller is None:
        return None
    closure = replace(c, coef=c.fuller, cv_error=c.fuller_error, fuller=None)
    return replace(p, closure=closure, origin=p.origin + ", fuller closure")


def gauge_reduced(p: Proposal, ctx: Context) -> Proposal | None:
    """The proposal without the constant terms that are a hidden state's carrier times
    a monomial of the observed states, in the carrier's equation (None when it has
    none). Beside a hidden coefficient ``h`` of ``theta`` such a term ``c m theta`` is
    not identifiable (``h + c m`` explains the data as well), and the smoother splits
    the two by its roughness penalty alone; without it the hidden state takes the term
    in, and its law may close where the split one's does not (prey-only Lotka-Volterra
    with stage one's x^2 and x^3 beside the carrier x)."""
    support = gauge_free_support(p.structure, ctx.feature_exprs, ctx.free_rows)
    if np.array_equal(support, p.structure.support):
        return None
    return evaluate(replace(p.structure, support=support), ctx, p.origin + ", gauge", p.order)


def gauge_free_support(st: Structure, feature_exprs, free_rows) -> np.ndarray:
    """``st.support`` less the constant terms of each hidden state's own equation that
    are its carrier times a monomial of the observed states (see :func:`gauge_reduced`);
    equations seen through several terms, or fixed, keep theirs."""
    obs = set().union(*(sp.sympify(e).free_symbols for e in feature_exprs))
    support = st.support.copy()
    for a, (i, k) in enumerate(st.pivots):
        if not free_rows[i] or np.count_nonzero(st.loadings[:, :, a]) != 1:
            continue
        carrier = sp.sympify(feature_exprs[k])
        for j in np.flatnonzero(support[i]):
            if j == k or st.varying[i, j]:
                continue
            ratio = sp.cancel(sp.sympify(feature_exprs[j]) / carrier)
            if ratio.free_symbols <= obs and ratio.is_polynomial(*obs):
                support[i, j] = False
    return support


def _usable(proposals):
    """Best closure first, among proposals whose structure fits the data (misfit within
    twice the best one's)."""
    if not proposals:
        return []
    floor = min(p.fit.misfit for p in proposals)
    ok = [p for p in proposals if p.fit.misfit <= 2.0 * max(floor, 1.0)]
    return sorted(ok, key=lambda p: (p.score, p.structure.n_hidden))


def improve_constants(p: Proposal, ctx: Context, max_moves: int = 3) -> Proposal:
    """Add or drop one constant term at a time in the equations with hidden states while
    that cuts the closure error by at least 20% (until the discovery's ``max_time``
    runs out: then ``p`` as improved so far)."""
    rows = sorted({i for i, _ in p.structure.pivots} | {
        int(i) for i in np.flatnonzero(p.structure.varying.any(axis=1))})
    rows = [i for i in rows if ctx.free_rows[i]]
    for _ in range(max_moves):
        best = None
        for i in rows:
            for j in range(p.structure.support.shape[1]):
                if (i, j) in p.structure.pivots or p.structure.varying[i, j]:
                    continue
                if spent(CUT):
                    return p
                sup = p.structure.support.copy()
                sup[i, j] = not sup[i, j]
                trial = evaluate(replace(p.structure, support=sup), ctx,
                                 p.origin + ", terms moved", p.order)
                if trial.fit.misfit > 2.0 * max(p.fit.misfit, 1.0):
                    continue
                if best is None or trial.score < best.score:
                    best = trial
        if best is None or best.score > IMPROVE * p.score:
            return p
        p = best
    return p
