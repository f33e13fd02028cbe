"""A proposal: a structure, the hidden series it implies and their closure, evaluated
once per structure and context (:func:`evaluate`, cached on the context)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..._core.derivatives import rate
from ..._core.timing import timed
from ..context import Context
from .closure import ClosureFit, fit_closure, fit_rate_closure
from .smoother import HiddenFit, Structure, fit_hidden

CACHE_BYTES = 2**28  # evaluated structures kept per context (see evaluate)


@dataclass(frozen=True)
class Proposal:
    """A structure, the hidden series it implies and their closure."""

    structure: Structure
    fit: HiddenFit
    closure: ClosureFit
    hidden: list  # (T, n_hidden + order - 1) per trajectory: hidden states (and rate)
    order: int
    origin: str
    # a hidden state inside the hidden equation (:mod:`.nested`): ((its proposal on the
    # augmented data, its carrier as a sympy monomial, the augmented context),)
    nested: tuple = ()
    # stage one's own structure (its varying coefficients as hidden states) with its
    # closure or the fuller one: the method's own law (:func:`..ranking.rank`). Every
    # other proposal, and any made from it, is not
    stage_one: bool = False

    def derived(self, origin_suffix: str, **changes) -> Proposal:
        """A proposal made from this one (a rewrite, a nested or shifted state): its
        origin extended by ``origin_suffix``, ``changes`` applied, no longer stage one's
        own law."""
        return replace(self, origin=self.origin + origin_suffix, stage_one=False, **changes)

    @property
    def n_states(self) -> int:
        """Hidden states of the closed system."""
        return self.structure.n_hidden + self.order - 1 + len(self.nested)

    @property
    def score(self) -> float:
        return self.closure.cv_error


def evaluate(structure, ctx: Context, origin: str, order: int = 1) -> Proposal:
    """Hidden series of ``structure`` and their closure (computed once per structure,
    loadings included, and context)."""
    key = (structure.support.tobytes(), structure.loadings.tobytes(),
           structure.loadings.shape, structure.pivots, order)
    if key in ctx.evaluated:
        fit, closure, hidden = ctx.evaluated[key]
        return Proposal(structure, fit, closure, hidden, order, origin)
    fit = fit_hidden(structure, ctx.thetas, ctx.observed, ctx.times, ctx.sigma, ctx.spacing)
    p = close(structure, fit, ctx, origin, order)
    # the hidden series dominate an entry's size: a few hundred structures of a
    # 2000-sample series take a few MB; long series stop being kept at CACHE_BYTES
    size = sum(h.nbytes for h in p.hidden) + sum(h.nbytes for h in fit.hidden)
    if size * (len(ctx.evaluated) + 1) <= CACHE_BYTES:
        ctx.evaluated[key] = (p.fit, p.closure, p.hidden)
    return p


@timed("closure")
def close(structure, fit, ctx, origin, order=1):
    """Closure of a fitted structure; ``order=2`` adds the rate of the (single) hidden
    state as a second hidden state and closes the rate."""
    hidden = [h for h in fit.hidden]
    names = [f"h{a}" for a in range(structure.n_hidden)]
    if order == 2:
        rates = [_derivative(h, t) for h, t in zip(hidden, ctx.times, strict=True)]
        states = [np.hstack([h, r]) for h, r in zip(hidden, rates, strict=True)]
        closure = fit_rate_closure(hidden, rates, ctx.smoothed, ctx.times, ctx.closure_library,
                                   ["g0"] + names + list(ctx.observed_names), ctx.span)
        return Proposal(structure, fit, closure, states, 2, origin)
    rates = [_derivative(h, t, edge=True) for h, t in zip(hidden, ctx.times, strict=True)]
    closure = fit_closure(hidden, [r for r, _ in rates], ctx.smoothed, ctx.times,
                          ctx.closure_library, names, list(ctx.observed_names), ctx.span,
                          edges=[e for _, e in rates])
    return Proposal(structure, fit, closure, hidden, 1, origin)


def _derivative(series, t, edge=False):
    """The series' rate; with ``edge``, also the samples at either end whose rate was
    extrapolated (half the widest window)."""
    out, windows = rate(np.asarray(series, float), t)
    if edge:
        return out, max(windows, default=1) // 2
    return out


def without_hidden(support, ctx: Context) -> Proposal:
    """The observed states closing on their own: stage one's terms with constant
    coefficients (their integral-form fit), no hidden state and so no closure. Judged
    like any proposal, it is the answer when nothing varies, and "no law found", with
    its failed checks, when that constant-coefficient law does not reproduce the data."""
    n_obs, n_feat = support.shape
    structure = Structure(np.asarray(support, bool), np.zeros((n_obs, n_feat, 0)), ())
    fit = fit_hidden(structure, ctx.thetas, ctx.observed, ctx.times, ctx.sigma, ctx.spacing)
    closure = ClosureFit(np.zeros((0, 0)), (), ctx.closure_library, 0.0, [])
    hidden = [np.zeros((len(t), 0)) for t in ctx.times]
    return Proposal(structure, fit, closure, hidden, 1, "no hidden state")
