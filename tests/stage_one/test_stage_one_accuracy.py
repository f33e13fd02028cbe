"""Stage one against ground truth: time-varying coefficients of the paper's oscillator.

Bars (issue 2): at 1% noise, R^2 of A(t) >= 0.95 and the switch found within 2% of
the series length. Default settings throughout.
"""

import numpy as np
import pysindy as ps
import pytest
from conftest import check_lorenz, r2, transition_time

from latentsindy import DynamicSINDy, systems

T_END, N_TIMES = 25.0, 1000


def fit_oscillator(A):
    data = systems.harmonic_oscillator(A=A, B=1.0, t_end=T_END, n_times=N_TIMES, noise=0.01,
                                       seed=1)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(n_samples=16)
    return data, coefs


@pytest.mark.parametrize("shape", [systems.Switch(-1.0, -4.0, at=12.0),
                                   systems.Sigmoid(-1.0, -4.0, at=12.0, sharpness=1.0)],
                         ids=["switch", "sigmoid"])
def test_oscillator_time_varying_A(shape):
    data, coefs = fit_oscillator(shape)
    assert coefs.active_terms() == [("x", "y"), ("y", "x")]
    a = coefs.term("x", "y")
    assert r2(a, data.parameters["A"]) >= 0.95
    found = transition_time(data.t, a, -1.0, -4.0)
    assert abs(found - 12.0) / T_END <= 0.02
    assert np.max(np.abs(coefs.term("y", "x") - 1.0)) < 0.05
    # away from the transition the truth lies inside the posterior band (mean +- 5 std,
    # plus 1% for the smoothing bias the band does not model)
    far = np.abs(data.t - 12.0) > 2.0
    err = np.abs(a - data.parameters["A"])[far]
    band = 5 * coefs.term_std("x", "y")[far] + 0.01 * np.abs(a[far])
    assert np.mean(err <= band) > 0.9


def test_lorenz_keeps_small_collinear_term():
    """Lorenz with a sigmoid sigma(t) at 1% noise: ydot's -y (5% of ydot's RMS, nearly
    collinear with rho x) survives pruning through the least-squares check, so rho is
    not biased; exact support, sigma(t) R^2 >= 0.9, constants within 5%."""
    sigma = systems.Sigmoid(8.0, 14.0, at=10.0, sharpness=0.5)
    data = systems.lorenz(sigma=sigma, n_times=2000, t_end=20.0, noise=0.01)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y", "z"]).coefficients(8)
    check_lorenz(coefs, data)


def test_observed_interaction_is_not_absorbed_into_a_varying_coefficient():
    """Lotka-Volterra, both states observed, alpha(t) drifting (1% noise): xdot = c(t) x
    with c = alpha(t) - beta y fits as well as alpha(t) x - beta x y; the observed x y
    terms must come back (support exact, beta, gamma, delta within 15%).

    Measured: exact support; beta 9.6%, gamma 1.7%, delta 1.5% off; alpha R^2 0.66
    (without the absorbed-term check: xdot = c(t) x and ydot = d(t) y only).
    """
    data = systems.lotka_volterra(alpha=systems.Sinusoid(1.0, 0.3, frequency=1 / 15.0),
                                  n_times=3000, t_end=30.0, noise=0.01)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(4)
    assert coefs.active_terms() == [("x", "x"), ("x", "x y"), ("y", "y"), ("y", "x y")]
    for (state, feature), value in {("x", "x y"): -0.1, ("y", "y"): -1.5,
                                    ("y", "x y"): 0.075}.items():
        assert abs(coefs.term(state, feature).mean() / value - 1) < 0.15, (state, feature)
    assert ("x", "x y") in model.restored_terms_
