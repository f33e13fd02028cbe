"""Draws of the randomised discovery benchmark (benchmarks/discovery.py) as tests:
systems that no tutorial tunes for, default settings, scored in the discovered variables
against the truth moved into them."""

import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from _families import FAMILIES, draw  # noqa: E402
from _scoring import score  # noqa: E402

from latentsindy import discover_hidden  # noqa: E402


def _discover(family, index, noise):
    d = draw(family, index, noise)
    result = discover_hidden(d.observed, FAMILIES[family].library(), t=d.t,
                             feature_names=list(d.observed_names), verbose=False)
    return result, score(result, d)


@pytest.mark.parametrize("family", ["fitzhugh_nagumo", "lorenz_z", "modulated",
                                    "oscillator_sinusoid", "driven_oscillator"])
def test_family_at_one_percent_noise(family):
    """Issue 9 bars, one draw each: the right number of hidden states, exact structure
    (no extra or missing term in any equation), hidden R^2 >= 0.98, hidden-equation
    coefficients within 2%. The four families exercise: a hidden additive input whose
    real constant terms stage one pruned (FitzHugh-Nagumo); the wrong terms made to
    vary by stage one (Lorenz with z hidden); one hidden state in two equations
    (modulated oscillator); a hidden state no coefficient shows (the rate of a
    sinusoidal B)."""
    _, s = _discover(family, 0, 0.01)
    assert s["n_hidden"] == s["n_hidden_true"]
    assert s["exact"], s
    assert s["r2"] >= 0.98
    assert s["error"] <= 0.02


def test_one_epidemic_wave_at_five_percent_noise():
    """Issue 20: one SIR wave, only the infected observed, 5% noise. The smoother's
    hidden series for the true carrier (h = (dI/dt) / I) is too rough to close, and
    ``dI/dt = h`` with a four-term law fitted the wave alone (wrong yet confident); the
    winner restated as the coefficient of I from its own trajectories gives the exact
    law, which wins as the smaller system: exact structure, R^2 >= 0.98, coefficients
    within 5%."""
    _, s = _discover("epidemic", 0, 0.05)
    assert s["exact"], s
    assert s["r2"] >= 0.98
    assert s["error"] <= 0.05


def test_a_logistic_prey_is_found_exact_and_confident():
    """A predator with a logistic prey seen through the prey (a fresh system, 1% noise,
    draw 1): the law is exact, and moving x^2 between dx/dt and the hidden law is the
    hidden state shifted by a multiple of x (the same system), so no exchange doubt;
    before, all 18 exact calls of its 20 were flagged by it."""
    from _families import ALL_FAMILIES

    d = draw("logistic_lv", 1, 0.01)
    result = discover_hidden(d.observed, ALL_FAMILIES["logistic_lv"].library(), t=d.t,
                             feature_names=list(d.observed_names), verbose=False)
    s = score(result, d)
    assert s["exact"] and s["error"] <= 0.02, s
    assert result.confident, result.doubts


def test_a_hidden_level_is_found_in_chens_system():
    """Chen's system with z hidden (a fresh system, 1% noise, draw 0): the hidden
    coefficient h = c - a - z needs a constant in its law (``dh/dt = -b h - x y +
    b (c - a)``) that the closure's one-standard-error rule drops; judged with it
    (the richer support carries the level), the law is exact and confident, where
    before a second hidden state faster than the sampling came back, flagged."""
    from _families import ALL_FAMILIES

    d = draw("chen", 0, 0.01)
    result = discover_hidden(d.observed, ALL_FAMILIES["chen"].library(), t=d.t,
                             feature_names=list(d.observed_names), verbose=False)
    s = score(result, d)
    assert s["n_hidden"] == 1 and s["exact"] and s["error"] <= 0.02, s
    assert result.confident, result.doubts


def test_lorenz_seen_through_x_alone():
    """Issue 20: Lorenz with only x observed, 1% noise. dx/dt's constant varies (h0 =
    sigma y); h0's law needs a second hidden state, the varying coefficient of x in
    dh0/dt (h1 = sigma (rho - z), nested discovery), found with every candidate term of
    the hidden laws free, its terms selected, and both hidden states shifted out of
    their flat directions: two hidden states, exact structure, R^2 >= 0.95 (the issue's
    bar), held-out score <= 1.5, coefficients within 2%, confident."""
    result, s = _discover("lorenz_x", 5, 0.01)
    assert s["n_hidden"] == 2 and s["exact"], s
    assert s["r2"] >= 0.95 and s["error"] <= 0.02
    assert result.score <= 1.5 and result.confident
    assert "coefficient of x in dh0/dt" in result.summary()


def test_ten_percent_noise_finishes_and_reports():
    """10% noise: no crash, no hang; a closed system with scores and alternatives."""
    result, s = _discover("lotka_volterra", 1, 0.1)
    assert np.isfinite(result.score) and result.refinement is not None
    assert s["n_hidden"] == 1
    assert "held-out score" in result.summary()


@pytest.mark.parametrize("family", ["lorenz_x", "driven_oscillator", "epidemic",
                                    "van_der_pol", "brusselator", "rossler", "lv_predator",
                                    "duffing", "lorenz_y", "shimizu_morioka", "rucklidge",
                                    "arneodo", "logistic_lv"])
def test_new_family_truth_holds_in_the_natural_variables(family):
    """The benchmark's truth, moved into the variables latentsindy reports (a hidden
    state inside another's equation for Lorenz from x), is the system the noise-free
    series follow: its right-hand side matches their rates (a cubic spline's derivative)
    to 1e-3 of their RMS (the series are samples of an exact solution)."""
    import sympy as sp
    from _scoring import _natural, natural_series, truth_in_variables
    from scipy.interpolate import CubicSpline

    d = draw(family, 0, 0.0)
    series, names = natural_series(d)
    rhs = truth_in_variables(d, _natural(d), names)
    states = np.column_stack([d.observed_clean, series])
    symbols = [sp.Symbol(n, real=True) for n in list(d.observed_names) + names]
    for k, name in enumerate(list(d.observed_names) + names):
        f = sp.lambdify(symbols, rhs[name].subs(d.truth["values"]), "numpy")
        model = np.broadcast_to(f(*states.T), (len(d.t),))
        rate = CubicSpline(d.t, states[:, k])(d.t, 1)
        inner = slice(5, -5)
        err = np.sqrt(np.mean((model[inner] - rate[inner]) ** 2))
        assert err <= 1e-3 * np.sqrt(np.mean(rate[inner] ** 2)), (name, err)


def test_a_hidden_state_is_scored_as_the_coefficient_in_the_equation_as_found():
    """Lorenz from x found as dx/dt = h0 defines h0 = sigma (y - x) (the coefficient of 1
    in that equation), found as dx/dt = h0 - sigma x it defines h0 = sigma y: the truth is
    moved into whichever variables were found, and in the first it reads dh0/dt =
    -(1 + sigma) h0 + x h1 with h1 = sigma (rho - z - 1)."""
    import sympy as sp
    from _scoring import hidden_definitions, truth_in_variables

    d = draw("lorenz_x", 0, 0.0)
    x, y, z, h0 = sp.symbols("x y z h0", real=True)
    s, r = sp.symbols("sigma rho")
    absorbed = [("coef", "x", "1", ()), ("coef", "h0", "x", (h0,))]
    shown = [("coef", "x", "1", (x,)), ("coef", "h0", "x", (h0,))]
    names = ["h0", "h1"]
    phis = hidden_definitions(d, absorbed, names)
    values = d.truth["values"]
    assert sp.simplify((phis[0] - s * (y - x)).subs(values)) == 0
    assert sp.simplify((phis[1] - s * (r - z - 1)).subs(values)) == 0
    assert sp.simplify((hidden_definitions(d, shown, names)[0] - s * y).subs(values)) == 0
    h1 = sp.Symbol("h1", real=True)
    law = sp.expand(truth_in_variables(d, absorbed, names)["h0"].subs(values))
    assert sp.expand(law - (-(1 + values[s]) * h0 + x * h1)) == 0


def _found(equations, states):
    """A stand-in result: hidden states (name, (equation, feature), rate_of) and each
    state's found equation {term: coefficient}."""
    hidden = tuple(SimpleNamespace(name=n, terms=(t,) if t else (), rate_of=r)
                   for n, t, r in states)
    return SimpleNamespace(hidden_states=hidden, equation=lambda s: equations[s])


def test_two_hidden_states_in_one_equation_keep_their_own_monomials():
    """Truth dx/dt = a y + x z found as dx/dt = h0 + x h1: h0 = a y (it does not take in
    the x monomial, which h1 carries) and h1 = z."""
    import sympy as sp
    from _scoring import definitions, hidden_definitions

    x, y, z, a = sp.symbols("x y z a", real=True)
    h0, h1 = sp.symbols("h0 h1", real=True)
    d = SimpleNamespace(truth={"rhs": {x: a * y + x * z, y: -y, z: -z}, "hidden": [y, z]},
                        observed_names=("x",))
    found = _found({"x": {h0: 1.0, x * h1: 1.0}},
                   [("h0", ("x", "1"), None), ("h1", ("x", "x"), None)])
    phis = hidden_definitions(d, definitions(found), ["h0", "h1"])
    assert sp.expand(phis[0] - a * y) == 0 and sp.expand(phis[1] - z) == 0


def test_a_rate_follows_its_state_through_the_observed_states():
    """Truth dy/dt = u - c y, du/dt = v, dv/dt = -w u, found as dy/dt = h0 (h0 = u - c y)
    with g0 its rate: g0 = v - c (u - c y), the observed part differentiated too."""
    import sympy as sp
    from _scoring import definitions, hidden_definitions

    y, u, v, c, w = sp.symbols("y u v c w", real=True)
    h0 = sp.Symbol("h0", real=True)
    d = SimpleNamespace(truth={"rhs": {y: u - c * y, u: v, v: -w * u}, "hidden": [u, v]},
                        observed_names=("y",))
    found = _found({"y": {h0: 1.0}}, [("h0", ("y", "1"), None), ("g0", None, "h0")])
    phis = hidden_definitions(d, definitions(found), ["h0", "g0"])
    assert sp.expand(phis[0] - (u - c * y)) == 0
    assert sp.expand(phis[1] - (v - c * (u - c * y))) == 0


def test_a_hidden_state_shifted_by_terms_the_truth_lacks():
    """Van der Pol (dx/dt = y, dy/dt = mu (1 - x^2) y - x) found in Lienard form, dx/dt =
    h + a x + b x^3 with dh/dt = -x: h = y - s0 x - s1 x^3 with shifts the found
    structure fixes (s0 = mu, s1 = -mu / 3), so the truth in h is exactly the found
    system. Found without the x^3 term, no shift removes the truth's x^2 h term: not the
    truth in any variable."""
    import sympy as sp
    from _scoring import definitions, hidden_shift_terms, truth_in_variables

    x, y, h, mu = sp.symbols("x y h mu", real=True)
    d = SimpleNamespace(truth={"rhs": {x: y, y: mu * (1 - x**2) * y - x}, "hidden": [y]},
                        observed_names=("x",))
    lienard = {"x": {h: 1.0, x: 1.5, x**3: -0.5}, "h": {x: -1.0}}
    found = _found(lienard, [("h", ("x", "1"), None)])
    found.rhs = {n: sum(c * f for f, c in eq.items()) for n, eq in lienard.items()}
    truth = truth_in_variables(d, definitions(found), ["h"], found.rhs)
    assert sp.expand(truth["x"] - (h + mu * x - mu * x**3 / 3)) == 0
    assert sp.expand(truth["h"] + x) == 0
    assert hidden_shift_terms(d, definitions(found), ["h"]) == [x, x**3]
    short = {"x": {h: 1.0, x: 1.5}, "h": {x: -1.0}}
    found = _found(short, [("h", ("x", "1"), None)])
    found.rhs = {n: sum(c * f for f, c in eq.items()) for n, eq in short.items()}
    assert truth_in_variables(d, definitions(found), ["h"], found.rhs) is None


def test_only_observed_shift_terms_enter_the_r2_map():
    """A shift's coefficient that holds a true hidden variable or another shift (a wrong
    structure) is no observed series: left out of the R^2 map (it crashed the map's
    least squares with sympy objects on Lorenz from x at 5-10% noise)."""
    import sympy as sp
    from _scoring import SHIFT, observed_shift_terms

    x, y, h = sp.symbols("x y h", real=True)
    s0, s1, s2 = (sp.Dummy(SHIFT) for _ in range(3))
    phi = h - s0 * x**2 - s1 * y - s2 * (x + s0)
    assert observed_shift_terms([phi], [x]) == [x**2]
    assert observed_shift_terms([phi], [x, y]) == [x**2, y]


def test_a_hidden_state_shifted_by_a_term_the_truth_has_where_its_law_loses_one():
    """Lorenz seen through x and z (y hidden) found as dx/dt = h0 + 11.16 x, dz/dt =
    0.1059 h0 x + 2.178 x^2 - 2.501 z, dh0/dt = -21.58 h0 - 9.43 x z (5% noise, draw 3):
    h0 = sigma y + s x, s = -20.60 the root of s^2 + (sigma - 1) s - sigma rho that
    removes x from dh0/dt. Exactly Lorenz in that gauge: exact, coefficients within
    0.2%. The same without x z in dh0/dt (and an x term instead) is no such gauge."""
    import sympy as sp
    from _scoring import score_structure

    d = draw("lorenz_y", 3, 0.05)
    x, z, h0 = sp.symbols("x z h0", real=True)
    laws = {"x": {h0: 1.0, x: 11.16}, "z": {h0 * x: 0.1059, x**2: 2.1784, z: -2.5012},
            "h0": {h0: -21.577, x * z: -9.4295}}
    found = _found(laws, [("h0", ("x", "1"), None)])
    found.rhs = {n: sum(c * f for f, c in eq.items()) for n, eq in laws.items()}
    found.hidden_names = ("h0",)
    got = score_structure(found, d)
    assert got["exact"] and got["error"] < 2e-3 and got["observed_error"] < 2e-3
    laws["h0"] = {h0: -21.577, x: 5.0}
    found.rhs = {n: sum(c * f for f, c in eq.items()) for n, eq in laws.items()}
    assert not score_structure(found, d)["exact"]


def test_a_truth_that_is_no_polynomial_in_the_found_variables_is_not_exact():
    """A hidden state defined through terms the truth divides into (h x^2 where the truth
    has x z: z = h x, so z's law in h has 1/x) gives no polynomial truth to fix shifts
    by: not the truth in any variable (None), not an error (Shimizu-Morioka at 5%
    noise, draw 4, stopped the benchmark's scoring with sympy's PolynomialError)."""
    import sympy as sp
    from _scoring import SHIFT, _solve_shifts

    x, h = sp.symbols("x h", real=True)
    shift = sp.Dummy(SHIFT)
    truth = {"h": h**2 / x + shift * x}
    assert _solve_shifts(truth, {"h": h + x}, [x, h]) is None
