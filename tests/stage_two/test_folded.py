"""A nested system whose second hidden state stands for a power of the first is doubted
(one hidden state with a law one degree higher scores as well); a real second hidden
state (Lorenz seen through x) is not."""

from types import SimpleNamespace

import numpy as np
import pysindy as ps
import pytest
import sympy as sp
from scipy.integrate import solve_ivp

from latentsindy._stage_two.doubts.folded import Folded, folded_doubts, folded_score
from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.fit.held_out import cross_validate
from latentsindy._stage_two.fit.refine import Problem

X, H0, H1 = sp.symbols("x h0 h1", real=True)
MU = 1.0
SIGMA, RHO, BETA = 10.0, 28.0, 8.0 / 3.0


def observed_with_noise(clean, level=0.01, seed=2):
    rng = np.random.default_rng(seed)
    return clean[:, :1] + level * clean[:, 0].std() * rng.standard_normal((len(clean), 1))


def verdict_of(system, t, clean, noisy):
    """The nested ``system`` refined from the true states, scored, as the judge's
    verdict would hold it."""
    problem = Problem(system, [t], [noisy], [clean])
    fit = problem.fit(system)
    cv, se, _ = cross_validate(problem, fit)
    return SimpleNamespace(system=fit.system, fit=fit, problem=problem, scored=True,
                           candidates=np.zeros_like(system.free),
                           proposal=SimpleNamespace(nested=("nested",)), cv=cv, cv_se=se,
                           size=fit.system.n_free + 2)


def nested_system(rows):
    """(x, h0, h1) with ``rows`` [{feature: value}] for x', h0', h1' (all free but the
    definition h0 in x')."""
    features = tuple(dict.fromkeys(f for row in rows for f in row))
    coef = np.zeros((3, len(features)))
    for i, row in enumerate(rows):
        for f, value in row.items():
            coef[i, features.index(f)] = value
    free = coef != 0
    free[0, features.index(H0)] = False
    return ParametricSystem(("x", "h0", "h1"), 1, features, coef, free)


def rayleigh():
    """Rayleigh's oscillator x' = v, v' = -x + mu (v - v^3) as a nested system: h0 = v,
    h1 = mu (1 - v^2) the coefficient of h0 in h0' (exact: h1' = -2 mu v v')."""
    t = np.linspace(0.0, 40.0, 2000)
    sol = solve_ivp(lambda _, s: [s[1], -s[0] + MU * (s[1] - s[1] ** 3)], (0, 40), [1.5, 0.3],
                    t_eval=t, method="DOP853", rtol=1e-10, atol=1e-10)
    x, v = sol.y
    clean = np.column_stack([x, v, MU * (1 - v**2)])
    system = nested_system([{H0: 1.0}, {H0 * H1: 1.0, X: -1.0},
                            {H0**2 * H1: -2 * MU, H0 * X: 2 * MU}])
    return verdict_of(system, t, clean, observed_with_noise(clean)), t, clean


def lorenz():
    """Lorenz seen through x as a nested system: h0 = sigma y, h1 = sigma (rho - z)."""
    t = np.linspace(0.0, 10.0, 2000)
    sol = solve_ivp(lambda _, s: [SIGMA * (s[1] - s[0]), s[0] * (RHO - s[2]) - s[1],
                                  s[0] * s[1] - BETA * s[2]], (0, 10), [-8.0, 7.0, 27.0],
                    t_eval=t, method="DOP853", rtol=1e-10, atol=1e-10)
    x, y, z = sol.y
    clean = np.column_stack([x, SIGMA * y, SIGMA * (RHO - z)])
    system = nested_system([{H0: 1.0, X: -SIGMA}, {X * H1: 1.0, H0: -1.0},
                            {X * H0: -1.0, H1: -BETA, sp.Integer(1): BETA * SIGMA * RHO}])
    return verdict_of(system, t, clean, observed_with_noise(clean)), t, clean


def test_a_real_second_hidden_state_is_not_doubted():
    verdict, _, _ = lorenz()
    assert verdict.cv == pytest.approx(1.0, abs=0.15)
    folded = folded_score(verdict, ps.PolynomialLibrary(2))
    # no cubic law in (x, h0) follows Lorenz's x: far outside the band
    assert folded.score > 10 * (verdict.cv + verdict.cv_se)
    assert folded_doubts(folded, verdict.cv, verdict.cv_se, verdict.size, ("y", "z")) == ()


@pytest.fixture(scope="module")
def rayleigh_verdict():
    return rayleigh()


def test_a_second_hidden_state_that_stands_for_a_power_of_the_first_is_doubted(
        rayleigh_verdict):
    verdict, _, _ = rayleigh_verdict
    assert verdict.cv == pytest.approx(1.0, abs=0.15)  # the nested form is exact
    folded = folded_score(verdict, ps.PolynomialLibrary(2))
    assert folded.degree == 3
    # one state, x' = h0 (its coefficient is the definition), the ten cubic monomials
    # of (x, h0), h0's initial value
    assert folded.size == 11
    # the folded law is Rayleigh's: h0' = -x + mu h0 - mu h0^3, nothing else
    law = dict(zip(folded.system.features, folded.system.coef[1], strict=True))
    assert law[X] == pytest.approx(-1.0, abs=0.05)
    assert law[H0] == pytest.approx(MU, abs=0.05)
    assert law[H0**3] == pytest.approx(-MU, abs=0.05)
    others = [abs(v) for f, v in law.items() if f not in (X, H0, H0**3)]
    assert max(others) < 0.05
    assert folded.score <= verdict.cv + verdict.cv_se
    (doubt,) = folded_doubts(folded, verdict.cv, verdict.cv_se, verdict.size, ("v", "w"))
    assert "one hidden state (v) whose law has terms up to degree 3" in doubt
    assert "w may stand for a power of v" in doubt
    assert "closure_library=ps.PolynomialLibrary(degree=3)" in doubt


def test_only_scored_nested_systems_with_a_polynomial_closure_are_folded(rayleigh_verdict):
    verdict, _, _ = rayleigh_verdict
    assert folded_score(verdict, ps.FourierLibrary()) is None
    not_nested = SimpleNamespace(**{**vars(verdict), "proposal": SimpleNamespace(nested=())})
    assert folded_score(not_nested, ps.PolynomialLibrary(2)) is None
    unscored = SimpleNamespace(**{**vars(verdict), "scored": False})
    assert folded_score(unscored, ps.PolynomialLibrary(2)) is None


def test_an_observed_equation_that_holds_the_nested_state_is_not_folded(rayleigh_verdict):
    verdict, _, _ = rayleigh_verdict
    system = verdict.system
    coef, free = system.coef.copy(), system.free.copy()
    c = system.features.index(H0 * H1)
    coef[0, c], free[0, c] = 0.1, True  # x' = h0 + 0.1 h0 h1
    changed = SimpleNamespace(**{**vars(verdict), "system": ParametricSystem(
        system.state_names, 1, system.features, coef, free)})
    assert folded_score(changed, ps.PolynomialLibrary(2)) is None


@pytest.mark.parametrize("score, doubted", [(1.09, True), (1.11, False), (0.5, True)])
def test_the_band_is_the_chosen_systems_score_plus_one_standard_error(score, doubted):
    folded = Folded(score, 0.05, 3, 12, None)
    assert bool(folded_doubts(folded, 1.0, 0.1, 9, ("h0", "h1"))) is doubted


def test_scores_below_the_tie_count_as_equal():
    # on noise-free data scores are tiny and their differences the integrator's
    assert folded_doubts(Folded(0.04, 0.01, 3, 12, None), 0.001, 0.0005, 9, ("h0", "h1"))
    assert folded_doubts(Folded(0.06, 0.01, 3, 12, None), 0.001, 0.0005, 9, ("h0", "h1")) == ()
    assert folded_doubts(None, 1.0, 0.1, 9, ("h0", "h1")) == ()
