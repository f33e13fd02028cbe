"""Nested discovery: a hidden state inside another hidden state's equation.

A hidden state found from the observed equations can have a law that no closure in the
observed states and itself reproduces, because it depends on a further variable that
no observed equation shows. Lorenz seen through x alone: ``xdot = h0 - sigma x`` with
``h0 = sigma y``, and ``dh0/dt = -h0 + x h1`` where ``h1 = sigma (rho - z)`` is the
coefficient of x in h0's equation, varying in time. That is the first step of
discovery again, applied to the augmented system: the observed states together with
the hidden state's estimated series are treated as measured, one term of the hidden
state's equation at a time carries a smooth time-varying coefficient (the structured
smoother, :mod:`.smoother`), and that coefficient's series is closed (:mod:`.closure`).
The judge then refines the whole system (observed plus both hidden states) against the
observed data alone and scores it on held-out segments, like every other proposal:
nothing here is accepted on the augmented data's word.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import sympy as sp

from ..._core.library import feature_expressions, state_symbols
from ..._core.symbolic import VectorField
from ..context import Context
from ..fit.field import ParametricSystem, polynomial_rows, system_from_rows
from ..rewrite.gauge import shifted_laws
from .hypotheses import _usable, pruned
from .proposal import Proposal
from .smoother import single_term

PARENT = "q0"  # the parent hidden state's name inside the augmented system
KEEP = 2  # nested proposals per parent passed on to the judge


def nested_proposals(parent: Proposal, ctx: Context, keep: int = KEEP) -> list[Proposal]:
    """Proposals with one more hidden state: a time-varying coefficient of one term of
    ``parent``'s (single, first-order) hidden equation, best closures first."""
    if parent.structure.n_hidden != 1 or parent.order != 1 or parent.nested:
        return []
    aug = augmented_context(parent, ctx)
    row = len(ctx.observed_names)
    support = _augmented_support(parent, ctx, aug)
    columns = [aug.feature_exprs.index(e) for e in _closure_exprs(parent, ctx)]
    support[row, columns] = True
    carriers = []
    for k in columns:
        # every closure term as a constant beside the carrier, then those that explain
        # less than the threshold of the equation's rate pruned (STLSQ with the
        # smoother inside): the parent's own closure is no guide, the data refused it
        trial = pruned(single_term(row + 1, len(aug.feature_exprs), row, k, support), aug,
                       "nested")
        if trial is not None:
            carriers.append(trial)
    return [_as_proposal(parent, p, ctx, aug) for p in _usable(carriers)[:keep]]


def augmented_context(parent: Proposal, ctx: Context) -> Context:
    """The data with the parent's hidden series as one more measured state (named
    ``q0``); its library holds the observed library, the parent's carrier times
    ``q0``, and the closure library in (observed, ``q0``)."""
    names = list(ctx.observed_names) + [PARENT]
    symbols = state_symbols(names)
    q0 = symbols[-1]
    (_, k), = parent.structure.pivots
    states = [np.hstack([x, h]) for x, h in zip(ctx.smoothed, parent.hidden, strict=True)]
    measured = [np.hstack([x, h]) for x, h in zip(ctx.observed, parent.hidden, strict=True)]
    exprs = []
    for e in list(ctx.feature_exprs) + [q0 * ctx.feature_exprs[k]] + _closure_exprs(parent, ctx):
        e = sp.expand(sp.sympify(e))
        if e not in exprs:
            exprs.append(e)
    library = VectorField(symbols, exprs)
    thetas = [library(0.0, s) for s in states]
    sigma = np.append(ctx.sigma, _hidden_noise(parent, ctx))
    return replace(ctx, observed_names=tuple(names),
                   feature_names=tuple(str(e) for e in exprs), feature_exprs=tuple(exprs),
                   observed=measured, smoothed=states, thetas=thetas, sigma=sigma,
                   free_rows=np.append(ctx.free_rows, True))


def _hidden_noise(parent, ctx):
    """Noise of the parent's hidden series as a measurement: the noise of a rate from a
    local polynomial over the differentiator's window (``sigma sqrt(12 / w^3) / dt``)
    in the carrier's equation, over the carrier's RMS size (the hidden state is that
    rate divided by its carrier)."""
    (i, k), = parent.structure.pivots
    w = max(ctx.span, 3)
    dt = np.mean([(t[-1] - t[0]) / max(len(t) - 1, 1) for t in ctx.times])
    theta = np.sqrt(np.mean(np.concatenate([th[:, k] for th in ctx.thetas]) ** 2))
    return ctx.sigma[i] * np.sqrt(12.0 / w**3) / dt / max(theta, 1e-300)


def _closure_exprs(parent, ctx):
    """The closure library's features in (observed, ``q0``): the candidate terms of the
    parent's equation."""
    return [sp.expand(e) for e in feature_expressions(
        parent.closure.library, list(parent.closure.feature_names),
        [PARENT] + list(ctx.observed_names))]


def _augmented_support(parent, ctx, aug):
    """The parent's observed equations in the augmented library (its carrier now a term
    in ``q0``), and an empty row for the parent's equation."""
    n_obs = len(ctx.observed_names)
    index = {e: j for j, e in enumerate(aug.feature_exprs)}
    support = np.zeros((n_obs + 1, len(aug.feature_exprs)), dtype=bool)
    st = parent.structure
    for i in range(n_obs):
        for k in np.flatnonzero(st.support[i]):
            q0 = state_symbols([PARENT])[0] if (i, k) in st.pivots else 1
            support[i, index[sp.expand(q0 * sp.sympify(ctx.feature_exprs[k]))]] = True
    return support


def _as_proposal(parent, p, ctx, aug):
    """The nested proposal ``p`` (on the augmented data) as a proposal on the observed
    data: the parent's structure, both hidden series, the new closure, and the new
    state's definition."""
    (_, k), = p.structure.pivots
    q0, h0 = state_symbols([PARENT, "h0"])
    carrier = sp.sympify(aug.feature_exprs[k]).xreplace({q0: h0})
    feature = monomial_name(carrier, state_symbols(list(ctx.observed_names) + ["h0"]))
    hidden = [np.hstack([h, g]) for h, g in zip(parent.hidden, p.hidden, strict=True)]
    return parent.derived(f", nested ({feature} in the hidden equation)", hidden=hidden,
                          closure=p.closure, nested=((p, carrier, aug),))


def monomial_name(expr, symbols):
    """A monomial's name as the libraries write it (``x h0^2``; ``1``), its variables in
    the order of ``symbols``."""
    powers = sp.Poly(expr, *symbols).monoms()[0]
    parts = [s.name if e == 1 else f"{s.name}^{e}"
             for s, e in zip(symbols, powers, strict=True) if e]
    return " ".join(parts) or "1"


def nested_system(p: Proposal, ctx: Context, build):
    """The closed system of a nested proposal on the observed data: the augmented
    system's (observed, ``q0``, new state) renamed to (observed, ``h0``, ``h1``) with
    ``h0`` hidden again, its definition (the carrier's coefficient, 1) fixed; the terms
    stepwise selection may add; the initial guesses."""
    (inner, _, aug), = p.nested
    system, candidates, guesses = build(inner, aug)
    n_obs = len(ctx.observed_names)
    old = state_symbols(list(system.state_names))
    new_names = list(ctx.observed_names) + ["h0", "h1"]
    rename = dict(zip(old, state_symbols(new_names), strict=True))
    features = tuple(f.xreplace(rename) for f in system.features)
    coef, free = system.coef.copy(), system.free.copy()
    (i, k), = p.structure.pivots
    h0 = state_symbols(["h0"])[0]
    definition = features.index(sp.expand(h0 * sp.sympify(ctx.feature_exprs[k])))
    coef[i, definition], free[i, definition] = 1.0, False
    candidates[i, definition] = False
    # The hidden equations start with every candidate term free: their closures come from
    # first estimates of two hidden series (the parent's in a gauge the observed data do
    # not fix) and miss terms the integrated system needs. On Lorenz from x at 1% noise,
    # 8 of 10 draws refine to the noise level this way, the two tried from the closures
    # alone stopped 32-1500 times above it;
    # stepwise selection then removes what the data do not support.
    free[n_obs:] |= candidates[n_obs:]
    candidates[n_obs:] = False
    out = ParametricSystem(tuple(new_names), n_obs, features, coef, free)
    return out, candidates, guesses


def shifted_nested_system(verdict, ctx: Context):
    """A nested system in the gauge without the flat directions of its hidden states.

    The nested state ``h1`` is the coefficient of its carrier ``c`` in the parent's
    equation, so ``h1 + g`` (``g`` a polynomial in the other states) is that coefficient
    as well when the parent's equation also holds the terms ``c g``: the same closed
    system with those terms moved into ``h1``'s law. Both fit the data equally, so
    refinement can end anywhere along that line (Lorenz from x: ``13 x^2`` in ``dh0/dt``
    with a standard error of 110) and the coefficients are undetermined. The parent has
    the same freedom with the observed terms of its own equation (``dx/dt = h0 + c x``
    for any ``c``, :mod:`.gauge`). Both shifts, the parent's first, are derived exactly
    (substitution and the chain rule). Returns (system, shifts) or None when there is
    nothing to absorb or a shifted law needs a term outside the system's library."""
    p, system = verdict.proposal, verdict.system
    if len(p.nested) != 1 or p.order != 1 or p.structure.n_hidden != 1:
        return None
    (_, carrier, _), = p.nested
    (i, k), = p.structure.pivots
    symbols = system.symbols
    n_obs = system.n_observed
    observed, parent, child = symbols[:n_obs], symbols[n_obs], symbols[n_obs + 1]
    child_step = (child, carrier, [*observed, parent], parent.name)
    attempts = [[child_step]]
    if ctx.free_rows[i] and np.count_nonzero(p.structure.loadings) == 1:
        # a parent seen through several terms would carry its shift into all of them
        parent_step = (parent, sp.sympify(ctx.feature_exprs[k]), observed,
                       system.state_names[i])
        attempts.insert(0, [parent_step, child_step])
    for steps in attempts:  # both shifts; the nested state's alone if that fails
        found = _shifted_system(system, steps)
        if found is not None:
            return found
    return None


def _shifted_system(system, steps):
    """``system`` with each (state, carrier, within, equation) step's shift applied in
    turn; None when nothing moves or a law leaves the system's features. The fixed terms
    (the definitions) hold the state they define, so no shift can take them in."""
    laws, shifts = system.rhs(), {}
    for state, carrier, within, equation in steps:
        shift = _absorbable(laws[equation], carrier, within)
        if shift != 0:
            laws = shifted_laws(laws, {state: shift}, within)
            shifts[state] = shift
    if not shifts:
        return None
    rows = polynomial_rows(laws, system.state_names)
    if rows is None or not {f for row in rows for f in row} <= set(system.features):
        return None
    shifted = system_from_rows(system.state_names, system.n_observed, rows, system,
                               leading=system.features, kept_rows=len(rows))
    return shifted, shifts


def _absorbable(law, carrier, within):
    """The sum of the terms of ``law`` in the states ``within`` alone that are
    ``carrier`` times a polynomial in them, divided by ``carrier``."""
    shift = sp.Integer(0)
    for term, value in sp.expand(law).as_coefficients_dict().items():
        if term.free_symbols - set(within):
            continue
        ratio = sp.cancel(term / carrier)
        if ratio.free_symbols <= set(within) and ratio.is_polynomial(*within):
            shift += value * ratio
    return sp.expand(shift)
