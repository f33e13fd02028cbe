"""A hidden state and its rate whose law is the derivative of a first-order law."""

from types import SimpleNamespace

import numpy as np
import pysindy as ps
import sympy as sp

from latentsindy._stage_two.doubts.states import first_integral_doubt
from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.propose.proposal import Proposal
from latentsindy._stage_two.rewrite.first_integral import integrated_proposal, integrated_system

A_OBS, A, B, C0 = -3.0, 0.8, -0.3, 0.05
X, Y, H, R = sp.symbols("x y h0 h0_rate", real=True)


def rate_verdict(rate_law, closure_degree=2):
    """xdot = A y, ydot = h x, hdot = r, rdot = ``rate_law``; the trajectory has
    r = A h + B h^2 + C0 exactly."""
    features = (Y, H * X, R, H * R, R * H**2, R * X)
    coef = np.zeros((4, len(features)))
    coef[0, 0], coef[1, 1], coef[2, 2] = A_OBS, 1.0, 1.0
    for col, value in rate_law.items():
        coef[3, features.index(col)] = value
    free = coef != 0
    free[1, 1] = free[2, 2] = False  # h is the coefficient of x in dy/dt; hdot = r
    system = ParametricSystem(("x", "y", "h0", "h0_rate"), 2, features, coef, free)
    h = np.linspace(0.5, 1.5, 50)
    tr = np.column_stack([np.sin(h), np.cos(h), h, A * h + B * h**2 + C0])
    library = ps.PolynomialLibrary(degree=closure_degree)
    library.fit(np.zeros((3, 4)))
    proposal = SimpleNamespace(
        order=2, hidden=None, origin="carrier, with its rate", stage_one=False,
        structure=SimpleNamespace(n_hidden=1, pivots=((1, 1),)),
        closure=SimpleNamespace(library=library,
                                feature_names=library.get_feature_names(["g0", "h0", "x", "y"])))
    problem = SimpleNamespace(trajectories=lambda fit: [tr])
    return SimpleNamespace(proposal=proposal, system=system, problem=problem, fit=None), tr


def test_the_derivative_of_a_logistic_law_integrates_back():
    verdict, tr = rate_verdict({R: A, H * R: 2 * B})
    system, (guess,) = integrated_system(verdict)
    assert system.state_names == ("x", "y", "h0") and system.n_observed == 2
    rhs = system.rhs()
    assert sp.expand(rhs["x"] - A_OBS * Y) == 0 and sp.expand(rhs["y"] - H * X) == 0
    got = sp.Poly(rhs["h0"], H).all_coeffs()[::-1]
    np.testing.assert_allclose([float(c) for c in got], [C0, A, B], rtol=1e-10, atol=1e-12)
    col = system.features.index(H * X)
    assert not system.free[1, col] and system.coef[1, col] == 1.0  # the pivot stays fixed
    assert system.free[2].sum() == 3
    np.testing.assert_array_equal(guess, tr[:, :3])


def test_no_first_integral_when_g_depends_on_an_observed_state():
    verdict, _ = rate_verdict({R: A, R * X: 0.2})
    assert integrated_system(verdict) is None


def test_no_first_integral_when_a_term_lacks_the_rate():
    verdict, _ = rate_verdict({R: A, H * R: 2 * B, H * X: 0.1})
    assert integrated_system(verdict) is None


def test_beyond_the_closure_library():
    """g quadratic in h needs h^3 in the first-order law: a degree-2 closure lacks it."""
    verdict, _ = rate_verdict({R: A, R * H**2: 0.3})
    assert integrated_system(verdict) is None
    verdict, _ = rate_verdict({R: A, R * H**2: 0.3}, closure_degree=3)
    assert integrated_system(verdict) is not None


def test_the_proposal_is_first_order():
    verdict, tr = rate_verdict({R: A, H * R: 2 * B})
    _, guesses = integrated_system(verdict)
    p = integrated_proposal(Proposal(fit=None, **vars(verdict.proposal)), guesses, 2)
    assert p.order == 1 and p.origin.endswith(", integrated") and not p.stage_one
    np.testing.assert_array_equal(p.hidden[0], tr[:, 2:3])


def test_a_non_polynomial_observed_law_has_no_first_integral_restatement():
    """sin(y) in an observed equation: the restated system cannot be built as
    polynomial rows, so there is none (the judge goes on without it)."""
    verdict, _ = rate_verdict({R: A, H * R: 2 * B})
    system = verdict.system
    features = system.features[:-1] + (sp.sin(Y),)
    coef = system.coef.copy()
    coef[0, -1] = 0.1
    free = system.free.copy()
    free[0, -1] = True
    verdict.system = ParametricSystem(system.state_names, 2, features, coef, free)
    assert integrated_system(verdict) is None


def test_a_winner_with_a_first_integral_is_a_doubt():
    verdict, _ = rate_verdict({R: A, H * R: 2 * B})
    (doubt,) = first_integral_doubt(verdict, ["h", "h_rate"])
    assert "dh_rate/dt is the time derivative of a first-order law for h" in doubt
    assert "not preferred" in doubt
    verdict, _ = rate_verdict({R: A, R * X: 0.2})
    assert first_integral_doubt(verdict, ["h", "h_rate"]) == ()
