"""A hidden state that is an exact function of the other states (a lifted system) is
substituted out; terms no candidate system held are checked for, and a law that needs
one is doubted."""

import warnings
from types import SimpleNamespace

import numpy as np
import pysindy as ps
import pytest
import sympy as sp
from scipy.integrate import solve_ivp

from latentsindy import discover_hidden
from latentsindy._stage_two import restate
from latentsindy._stage_two.doubts.beyond import beyond_terms
from latentsindy._stage_two.doubts.states import observed_function_doubts
from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.fit.refine import Problem
from latentsindy._stage_two.rewrite.observed_function import (
    function_reduced_system,
    observed_function,
    state_function,
)

MU = 1.2
Y, H0, H1 = sp.symbols("y h0 h1", real=True)


def lifted_vdp(extra=None):
    """Van der Pol seen through its velocity y, lifted: y' = h0 + h1 y, h0' = -y,
    h1' = 2 mu h0 y (+ ``extra``: {feature: value} in h1's law). Along it
    h1 + mu h0^2 is conserved (h0 = -x, h1 = mu (1 - x^2))."""
    features = (H0, H1 * Y, Y, H0 * Y, H1)
    coef = np.zeros((3, 5))
    coef[0, 0] = coef[0, 1] = 1.0
    coef[1, 2], coef[2, 3] = -1.0, 2 * MU
    for feature, value in (extra or {}).items():
        coef[2, features.index(feature)] = value
    free = coef != 0
    free[0, :2] = False
    return ParametricSystem(("y", "h0", "h1"), 1, features, coef, free)


def vdp(t, noise=0.0, seed=3):
    sol = solve_ivp(lambda _, s: [s[1], MU * (1 - s[0] ** 2) * s[1] - s[0]], (t[0], t[-1]),
                    [2.0, 0.0], t_eval=t, method="DOP853", rtol=1e-10, atol=1e-10)
    clean = sol.y.T
    rng = np.random.default_rng(seed)
    return clean, clean + noise * clean.std(axis=0) * rng.standard_normal(clean.shape)


def test_a_hidden_state_that_is_a_function_of_the_others_is_found_exactly():
    """h1' = 2 mu h0 y with h0' = -y is the derivative of -mu h0^2 (to rounding); h0 is
    no polynomial of y and h1, and a term in h1 itself breaks the identity."""
    found = state_function(lifted_vdp(), 2)
    assert sp.Poly(found, Y, H0).as_dict().keys() == {(0, 2)}
    assert float(sp.Poly(found, H0).coeff_monomial(H0**2)) == pytest.approx(-MU, abs=1e-12)
    assert state_function(lifted_vdp(), 1) is None
    assert state_function(lifted_vdp({H1: -0.3}), 2) is None
    assert observed_function(lifted_vdp(), 2) is None  # not a function of y alone
    with pytest.raises(ValueError, match="cannot be a function of itself"):
        observed_function(lifted_vdp(), 2, over=[0, 2])


def test_substituted_out_the_lifted_system_is_van_der_pol():
    """h1 = -mu h0^2 + c, c from the trajectory (mu): y' = h0 + mu y - mu h0^2 y, h0's
    law unchanged, to 1e-9."""
    t = np.linspace(0, 20, 800)
    clean, _ = vdp(t)
    x, y = clean.T
    tr = np.column_stack([y, -x, MU * (1 - x**2)])
    verdict = SimpleNamespace(system=lifted_vdp(), fit=None, candidates=None,
                              problem=SimpleNamespace(trajectories=lambda fit: [tr]))
    system, guesses, _ = function_reduced_system(verdict, 2)
    assert system.state_names == ("y", "h0")
    rhs = system.rhs()
    for law, expected in ((rhs["y"], H0 + MU * Y - MU * H0**2 * Y), (rhs["h0"], -Y)):
        residue = sp.Poly(sp.expand(law - expected), Y, H0).coeffs()
        assert all(abs(float(c)) < 1e-9 for c in residue)
    assert np.array_equal(guesses[0], tr[:, :2])
    assert function_reduced_system(verdict, 1) is None


def test_the_doubt_names_the_first_integral():
    (doubt,) = observed_function_doubts(lifted_vdp(), {"h0": "v", "h1": "u"})
    assert doubt.startswith("u is a function of the other states, u = -1.2*v**2 + constant")
    assert observed_function_doubts(lifted_vdp({H1: -0.3}), {}) == ()


@pytest.fixture(scope="module")
def vdp_velocity():
    t = np.linspace(0, 6 * (2 * np.pi + 1.6 * MU), 2000)
    _, noisy = vdp(t, noise=0.01)
    return t, noisy[:, 1:]


def test_van_der_pol_seen_through_its_velocity_comes_back_with_one_hidden_state(
        vdp_velocity, monkeypatch):
    """Default settings: the position enters dy/dt twice (-x and mu (1 - x^2) y), so
    two coefficients vary and the law found first has two hidden states tied by a first
    integral. Substituted out, the result is Van der Pol (h0 = -x), confident,
    coefficients within 1%. Without the substitution the lifted system is reported and
    doubted, not trusted."""
    t, y = vdp_velocity
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = discover_hidden(y, ps.PolynomialLibrary(degree=3), t=t,
                                 feature_names=["y"], verbose=False, seed=0)
    assert result.hidden_names == ("h0",) and result.confident, result.summary()
    ys, h = result.symbols
    expected = {"y": {h: 1.0, ys: MU, h**2 * ys: -MU}, "h0": {ys: -1.0}}
    for state, terms in expected.items():
        law = sp.Poly(result.rhs[state], ys, h)
        assert len(law.terms()) == len(terms)
        for monomial, value in terms.items():
            assert float(law.coeff_monomial(monomial)) == pytest.approx(value, rel=1e-2)
    monkeypatch.setattr(restate, "function_reduced", lambda verdict, options: None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        lifted = discover_hidden(y, ps.PolynomialLibrary(degree=3), t=t,
                                 feature_names=["y"], verbose=False, seed=0)
    assert len(lifted.hidden_names) == 2 and not lifted.confident
    assert any("is a function of the other states" in d for d in lifted.doubts)


A, B = 0.08, 0.6  # Sel'kov's glycolytic oscillator
X, H = sp.symbols("x h", real=True)


CLOSURE = [sp.Integer(1), X, H, X**2, X * H, H**2]


def selkov_data():
    t = np.linspace(0, 60, 1500)
    sol = solve_ivp(lambda _, s: [-s[0] + A * s[1] + s[0] ** 2 * s[1],
                                  B - A * s[1] - s[0] ** 2 * s[1]], (0, 60), [1.0, 1.0],
                    t_eval=t, method="DOP853", rtol=1e-10, atol=1e-10)
    clean = sol.y.T
    noisy = clean[:, :1] + 0.02 * clean[:, 0].std() * np.random.default_rng(5).standard_normal(
        (len(t), 1))
    return t, clean, noisy


def degree_two_stand_in():
    """The least-squares law of degree <= 2 for h' along the true series."""
    _, clean, _ = selkov_data()
    x, h = clean.T
    rate = B - A * h - x**2 * h
    columns = np.column_stack([sp.lambdify((X, H), f)(x, h) * np.ones_like(x) for f in CLOSURE])
    return dict(zip(CLOSURE, np.linalg.lstsq(columns, rate, rcond=None)[0], strict=True))


def selkov_verdict(hidden_law):
    """Sel'kov seen through x (noise 2%), x' = -x + a h + x^2 h, with ``hidden_law``
    ({feature: value}) for h, refined from the true series; the closure's candidates
    are the monomials of degree <= 2."""
    t, clean, noisy = selkov_data()
    closure = CLOSURE
    features = tuple(dict.fromkeys([X, H, X**2 * H, *closure, *hidden_law]))
    coef = np.zeros((2, len(features)))
    free = np.zeros_like(coef, dtype=bool)
    for f, value in {X: -1.0, H: A}.items():
        coef[0, features.index(f)], free[0, features.index(f)] = value, True
    coef[0, features.index(X**2 * H)] = 1.0
    for f, value in hidden_law.items():
        coef[1, features.index(f)], free[1, features.index(f)] = value, True
    system = ParametricSystem(("x", "h"), 1, features, coef, free)
    problem = Problem(system, [t], [noisy], [clean])
    fit = problem.fit(system)
    candidates = np.zeros_like(free)
    candidates[1, [features.index(f) for f in closure]] = True
    return SimpleNamespace(system=fit.system, problem=problem, fit=fit, scored=True,
                           candidates=candidates & ~fit.system.free)


def test_a_term_beyond_the_closure_library_that_the_data_call_for_is_found():
    """The true law of h needs x^2 h (degree 3): without it (the best degree-2 stand-in,
    every monomial of degree <= 2 refined) the data call for terms beyond the closure
    library by far more than a term's price; with it, for none."""
    extended, found = beyond_terms(selkov_verdict(degree_two_stand_in()), [sp.Integer(1),
                                   X, X**2, X**3], [True])
    assert found, "x^2 h should be called for"
    (row, col), change, price = found[0]
    assert (extended.state_names[row], extended.features[col]) == ("h", X**2 * H)
    assert change + price < -100
    _, found = beyond_terms(selkov_verdict({sp.Integer(1): B, H: -A, X**2 * H: -1.0}),
                            [sp.Integer(1), X, X**2, X**3], [True])
    assert found == []
