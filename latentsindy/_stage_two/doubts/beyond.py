"""Terms beyond the search: does the data call for a term no candidate system held?

Two bounds limit the systems stage two can reach. The closure library bounds the hidden
laws (default: polynomials of degree 2), and the structure search bounds how hidden
states enter the observed laws (as the coefficients of the terms it proposed). A law
outside them is approximated by the nearest one inside, and an approximation that
reproduces held-out data about as well as the noise allows can pass every other check.
Sel'kov's glycolytic oscillator seen through x at 5% noise came back confident as
``dx/dt = h x^2 - 1.50 x + 0.15`` with a six-term degree-2 law for h; the truth needs
``x^2 h`` in the hidden law (degree 3) and ``a h`` in dx/dt, and refined from the true
series it scores 1.00 +- 0.02 noise variances against the law found's 1.22 +- 0.06.

:func:`beyond_terms` adds, with zero coefficients, every monomial of the states one
degree above the hidden laws' candidates (in the hidden laws) and every hidden state
times every library term (in the observed laws), and asks
:func:`.terms.missing_terms` whether the data call for any of them: whether adding one
lowers the misfit by more than the price of a term, with strong evidence (``STRONG``).
On Sel'kov's case they call for three (28.8, 28.4 and 16.7 residual variances against
a price of 10), so the law found is reported as probably an approximation. The check
does not adopt such a term: the law that needs it may differ in more than that term
(here in two, and in the gauge).
"""

from __future__ import annotations

import itertools

import numpy as np
import sympy as sp

from ..fit.field import ParametricSystem
from ..fit.shooting import BlowUp
from ..fit.terms import missing_terms

# How far below a term's price an added term must lower the misfit (residual variances,
# i.e. twice the log Bayes factor in BIC's approximation) to count: "strong" evidence on
# Kass & Raftery's scale. The terms tested here lie outside the searched class and are
# many (twenty to forty), so one of them lowers the misfit by about its price by chance
# now and then: a correct damped Duffing law at 1% and 5% noise (one draw, the same noise
# pattern) had h0 x in dx/dt 0.7 below the price. The approximations measured were 7.9
# to 800 below it.
STRONG = 6.0


def beyond_terms(verdict, feature_exprs, free_rows):
    """Terms outside the chosen system's candidates that the data call for.

    Returns (system, found): ``system`` the chosen one with the extra terms as features
    (zero coefficients), ``found`` [(cell, misfit change, price)] for each extra term
    whose addition lowers the misfit by more than its price plus ``STRONG`` (cells index
    the extended system), the one the data call for most first. ``(None, [])`` when
    nothing can be checked (no score, a non-polynomial term, or the extended fit
    fails)."""
    system, pool = verdict.system, verdict.candidates
    if not verdict.scored or pool is None:
        return None, []
    pool = pool | system.free
    symbols = system.symbols
    n_obs, n_states = system.n_observed, len(symbols)
    degrees = [_degree(f, symbols) for f in system.features]
    hidden_pool = [d for c, d in enumerate(degrees) if pool[n_obs:, c].any()]
    if n_states == n_obs or any(d is None for d in hidden_pool):
        return None, []
    wanted = {}  # feature -> rows where it may enter
    top = max(hidden_pool, default=0) + 1
    for combo in itertools.combinations_with_replacement(symbols, top):
        wanted.setdefault(sp.Mul(*combo), set()).update(range(n_obs, n_states))
    for h in symbols[n_obs:]:
        for f in (sp.expand(h * e) for e in feature_exprs):
            wanted.setdefault(f, set()).update(i for i in range(n_obs) if free_rows[i])
    have = {f: c for c, f in enumerate(system.features)}
    new = [f for f in wanted if f not in have]
    features = tuple(system.features) + tuple(new)
    pad = np.zeros((n_states, len(new)))
    extended = ParametricSystem(system.state_names, n_obs, features,
                                np.hstack([system.coef, pad]),
                                np.hstack([system.free, pad.astype(bool)]))
    candidates = np.zeros_like(extended.free)
    for f, rows in wanted.items():
        candidates[sorted(rows), features.index(f)] = True
    candidates[:, :len(system.features)] &= ~pool & (system.coef == 0)
    if not candidates.any():
        return None, []
    # the same data, segments and scales as the chosen fit
    problem = verdict.problem.for_system(extended)
    try:
        fit = problem.fit(extended, starts=verdict.fit.starts)
        found = missing_terms(problem, fit, candidates)
    except (BlowUp, np.linalg.LinAlgError):
        return None, []
    return extended, [(cell, change, price) for cell, change, price in found
                      if change + price < -STRONG]


def _degree(feature, symbols):
    """Total degree of a monomial of the states (coefficient 1); None otherwise."""
    try:
        poly = sp.Poly(feature, *symbols)
    except sp.PolynomialError:
        return None
    if len(poly.terms()) != 1 or poly.coeffs()[0] != 1:
        return None
    return poly.total_degree()


