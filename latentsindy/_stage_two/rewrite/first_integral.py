"""First integrals: a hidden state and its rate whose law is the derivative of a
first-order one.

When no first-order hidden law reproduces the data, the judge also tries the hidden
state's rate as a second state (``dh/dt = r``, ``dr/dt = ...``). A law
``dr/dt = r g(h)`` is the time derivative of ``dh/dt = G(h) + c`` (``G' = g``): along
every solution ``r - G(h)`` is conserved, so one hidden state and one constant carry
the same dynamics (a logistic ``dh/dt = a h + b h^2`` differentiated is
``dr/dt = r (a + 2 b h)``). The smaller system is derived exactly (sympy integrates
``g``), its constant is the conserved quantity's mean along the fitted trajectory, and
it is refitted, its terms selected and scored like any candidate: the smallest system
that reproduces the data wins. It is offered only when ``g`` depends on ``h`` alone, the
observed equations do not use the rate, and ``G`` stays within the closure library's
degree.
"""

from __future__ import annotations

import numpy as np
import sympy as sp

from ..._core.library import feature_expressions
from ..fit.field import ParametricSystem, polynomial_rows, system_from_rows


def integrated_system(verdict):
    """The first-order system whose derivative is ``verdict``'s rate law, and its
    guesses (the fitted trajectories without the rate); None when the law is not of
    the form ``dr/dt = r g(h)``. Returns (system, guesses)."""
    p, system = verdict.proposal, verdict.system
    if p.order != 2 or p.structure.n_hidden != 1:
        return None
    n_obs = system.n_observed
    symbols = system.symbols
    h, r = symbols[n_obs], symbols[n_obs + 1]
    rhs = system.rhs()
    if sp.expand(rhs[h.name] - r) != 0 or any(r in rhs[s.name].free_symbols
                                              for s in symbols[:n_obs]):
        return None
    g = sp.cancel(sp.expand(rhs[r.name]) / r)
    if not g.free_symbols <= {h} or not g.is_polynomial(h) or g == 0:
        return None
    big_g = sp.expand(sp.integrate(g, h))
    if sp.Poly(big_g, h).degree() > _closure_degree(p):
        return None
    trajectories = verdict.problem.trajectories(verdict.fit)
    if not all(np.all(np.isfinite(tr)) for tr in trajectories):
        return None
    conserved = sp.lambdify((h, r), r - big_g, modules="numpy")
    c = float(np.mean(np.concatenate([
        np.broadcast_to(conserved(tr[:, n_obs], tr[:, n_obs + 1]), (len(tr),))
        for tr in trajectories])))
    reduced = ParametricSystem(system.state_names[:n_obs + 1], n_obs, (), np.zeros((0, 0)),
                               np.zeros((0, 0), dtype=bool))
    laws = {s.name: rhs[s.name] for s in symbols[:n_obs]}
    laws[h.name] = big_g + sp.Float(c)
    rows = polynomial_rows(laws, reduced.state_names)
    if rows is None:
        return None
    new = system_from_rows(reduced.state_names, n_obs, rows, system, kept_rows=n_obs)
    guesses = [tr[:, :n_obs + 1].copy() for tr in trajectories]
    return new, guesses


def integrated_proposal(p, guesses, n_observed):
    """The proposal as the integrated system's origin: first order, its hidden series."""
    return p.derived(", integrated", order=1, hidden=[g[:, n_observed:] for g in guesses])


def _closure_degree(p):
    """The highest power of one state among the closure library's features."""
    library = p.closure.library
    names = [f"s{k}" for k in range(int(getattr(library, "n_features_in_", 0)))]
    if not names:
        return 0
    exprs = feature_expressions(library, list(p.closure.feature_names), names)
    powers = [sp.Poly(e, *sp.symbols(names, real=True)).degree_list() for e in exprs]
    return max((max(d) for d in powers if sum(d) == max(d)), default=0)
