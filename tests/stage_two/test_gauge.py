"""The gauge shift of a hidden state, against the exact Lotka-Volterra law."""

from types import SimpleNamespace

import numpy as np
import pysindy as ps
import pytest
import sympy as sp

from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.rewrite.gauge import shifted_guesses, shifted_system

ALPHA, GAMMA, DELTA, D = 1.1, 0.7, 0.05, 0.03
X, H = sp.symbols("x h0", real=True)


def verdict_in_shifted_gauge(closure_degree=2):
    """Prey-only LV found as xdot = x h + d x^2 (h = h' - d x, h' = alpha - beta y): the
    hidden law in h follows from h' = alpha - beta y by the chain rule."""
    features = (X, X**2, X * H, sp.Integer(1), H, H**2)
    coef = np.zeros((2, len(features)))
    coef[0, 1], coef[0, 2] = D, 1.0
    coef[1, 3], coef[1, 0], coef[1, 4] = GAMMA * ALPHA, -DELTA * ALPHA - GAMMA * D, -GAMMA
    coef[1, 2], coef[1, 1] = DELTA - D, (DELTA - D) * D
    free = coef != 0
    free[0, 2] = False  # h is the coefficient of x in dx/dt
    system = ParametricSystem(("x", "h0"), 1, features, coef, free)
    support = np.array([[True, True, False]])
    loadings = np.zeros((1, 3, 1))
    loadings[0, 0, 0] = 1.0
    library = ps.PolynomialLibrary(degree=closure_degree)
    library.fit(np.zeros((3, 2)))
    proposal = SimpleNamespace(
        order=1, structure=SimpleNamespace(pivots=((0, 0),), loadings=loadings, support=support),
        closure=SimpleNamespace(library=library,
                                feature_names=library.get_feature_names(["h0", "x"])))
    ctx = SimpleNamespace(free_rows=np.array([True]), feature_exprs=(X, X**2, X**3),
                          observed_names=("x",))
    return SimpleNamespace(proposal=proposal, system=system), ctx


def test_shift_gives_back_the_lotka_volterra_law():
    verdict, ctx = verdict_in_shifted_gauge()
    system, shifts, dropped = shifted_system(verdict, ctx)
    rhs = system.rhs()
    assert sp.expand(shifts[H] - D * X) == 0 and dropped == [(0, 1)]
    assert sp.expand(rhs["x"] - X * H) == 0
    want = {sp.Integer(1): GAMMA * ALPHA, X: -DELTA * ALPHA, H: -GAMMA, X * H: DELTA}
    got = sp.Poly(rhs["h0"], X, H).as_expr().as_coefficients_dict()
    for term, value in want.items():
        assert float(got[term]) == pytest.approx(value, rel=1e-12)
    assert set(got) <= set(want) | {X**2} and abs(float(got.get(X**2, 0.0))) < 1e-12
    assert system.free[1].sum() >= 4 and not system.free[0, system.features.index(X * H)]


def test_shifted_series_are_the_shift_applied_to_the_trajectory():
    verdict, _ = verdict_in_shifted_gauge()
    tr = np.column_stack([np.linspace(1, 2, 5), np.linspace(0, 1, 5)])
    (out,) = shifted_guesses([tr], verdict.system, {H: D * X})
    np.testing.assert_allclose(out[:, 1], tr[:, 1] + D * tr[:, 0])
    assert shifted_guesses([np.full((3, 2), np.nan)], verdict.system, {H: D * X}) is None


def test_no_shift_outside_the_closure_library():
    """With a closure library of degree 1 the shifted law (x h terms) is not offered."""
    verdict, ctx = verdict_in_shifted_gauge(closure_degree=1)
    assert shifted_system(verdict, ctx)[0] is None


# ---------------------------------------------------------- an exchange that is a shift
_X, _H = sp.symbols("x h", real=True)
_FEATURES = (_H * _X, _X**2, _H, _X, sp.Integer(1))


def _logistic_prey(d):
    """A predator with a logistic prey through the prey, in the gauge ``h = 1 - x/K -
    y + d x``: dx/dt = h x - d x^2, and h's law by the chain rule (K = 4, b = 0.6,
    c = 0.9)."""
    from latentsindy._stage_two.rewrite.gauge import shifted_laws

    k, b, c = 4.0, 0.6, 0.9
    y = 1 - _X / k - _H
    base = {"x": _H * _X, "h": sp.expand(-_H * _X / k - (-c * y + b * _X * y))}
    laws = shifted_laws(base, {_H: sp.Float(d) * _X}, [_X]) if d else base
    coef = np.array([[float(sp.expand(laws[n]).coeff(_X, e).coeff(_H, f).subs({_X: 0, _H: 0}))
                      for e, f in ((1, 1), (2, 0), (0, 1), (1, 0), (0, 0))]
                     for n in ("x", "h")])
    free = coef != 0
    free[0, 0] = False  # h is the coefficient of x
    return ParametricSystem(("x", "h"), 1, _FEATURES, coef, free)


def _fit(system, starts):
    return SimpleNamespace(system=system, starts=np.asarray(starts, float))


def test_an_exchange_that_shifts_the_hidden_state_is_the_same_system():
    """Moving x^2 between dx/dt and h's law is the hidden state shifted by a multiple of
    x (the same dynamics): recognised when the refit's hidden starts are the shift of
    the chosen fit's (to a tenth of ``SHIFT_MATCH``), not when they differ by 5% of
    their spread."""
    from latentsindy._stage_two.rewrite.gauge import SHIFT_MATCH, same_up_to_shift, shift_between

    a, b = _logistic_prey(0.0), _logistic_prey(0.25)
    assert a.coef[0, 1] == 0 and b.coef[0, 1] == pytest.approx(-0.25)
    shifts = shift_between(a, b)
    assert list(shifts) == [_H] and sp.expand(shifts[_H] + 0.25 * _X) == 0
    rng = np.random.default_rng(0)
    starts = np.column_stack([rng.uniform(0.5, 2.0, 40), rng.uniform(-0.5, 0.5, 40)])
    shifted = starts.copy()
    shifted[:, 1] += 0.25 * starts[:, 0]  # h' = h - s(x), s = -0.25 x
    assert same_up_to_shift(_fit(a, starts), _fit(b, shifted))
    off = shifted.copy()
    off[:, 1] += 0.1 * SHIFT_MATCH * np.std(shifted[:, 1]) * rng.standard_normal(40)
    assert same_up_to_shift(_fit(a, starts), _fit(b, off))  # a tenth of the tolerance
    off = shifted.copy()
    off[:, 1] += 0.05 * np.std(shifted[:, 1]) * np.sign(rng.standard_normal(40))
    assert not same_up_to_shift(_fit(a, starts), _fit(b, off))


def test_no_shift_where_the_observed_equations_agree_or_a_state_is_seen_twice():
    """An exchange inside the hidden law leaves the observed equations alike: no shift
    (a genuine ambiguity). A hidden state in two observed equations: none either."""
    from latentsindy._stage_two.rewrite.gauge import same_up_to_shift, shift_between

    a = _logistic_prey(0.0)
    other = ParametricSystem(a.state_names, 1, a.features, a.coef.copy(), a.free)
    other.coef[1, 1] += 0.1  # another hidden law, same observed equation
    assert shift_between(a, other) is None
    starts = np.ones((5, 2))
    assert not same_up_to_shift(_fit(a, starts), _fit(other, starts))
    y, h = sp.symbols("y h", real=True)
    features = (h * _X, h * y, _X, y)
    coef = np.array([[1.0, 0.0, 0.2, 0.0], [0.0, 1.0, 0.0, 0.3], [0.0, 0.0, -1.0, 0.0]])
    twice = ParametricSystem(("x", "y", "h"), 2, features, coef, coef != 0)
    moved = ParametricSystem(twice.state_names, 2, features, coef + 0.1 * (coef != 0),
                             twice.free)
    assert shift_between(twice, moved) is None


def test_a_refit_that_blew_up_is_no_shift():
    """A refit whose hidden starts are not finite is not the same system."""
    from latentsindy._stage_two.rewrite.gauge import same_up_to_shift

    a, b = _logistic_prey(0.0), _logistic_prey(0.25)
    starts = np.column_stack([np.linspace(0.5, 2.0, 10), np.linspace(-0.5, 0.5, 10)])
    shifted = starts.copy()
    shifted[:, 1] += 0.25 * starts[:, 0]
    shifted[3, 1] = np.nan
    assert not same_up_to_shift(_fit(a, starts), _fit(b, shifted))
