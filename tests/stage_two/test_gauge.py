"""The gauge shift of a hidden state, against the exact Lotka-Volterra law."""

from types import SimpleNamespace

import numpy as np
import pysindy as ps
import pytest
import sympy as sp

from latentsindy._stage_two.field import ParametricSystem
from latentsindy._stage_two.gauge import shifted_guesses, shifted_system

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
