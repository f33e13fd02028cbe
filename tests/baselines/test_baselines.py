"""The paper's baselines against analytic truth: windowed SINDy and SLDS/rSLDS."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pysindy as ps
import pytest

from latentsindy import systems
from latentsindy.baselines import (
    Segmentation,
    WindowedSINDy,
    import_ssm,
    switch_time_errors,
    switching_lds,
)

LINEAR = ps.PolynomialLibrary(degree=1, include_bias=False)


# ssm is an optional extra (README: its own install line, which CI runs): where it is
# not installed at all (a GPU machine's image, say) the tests that fit an SLDS skip,
# saying why; an installed ssm that fails to import fails them
needs_ssm = pytest.mark.skipif(importlib.util.find_spec("ssm") is None,
                               reason="ssm is not installed (README)")


@pytest.fixture(scope="module")
def switched():
    """Oscillator whose A jumps from -1 to -4 at the middle (a window boundary for 2^k
    windows)."""
    return systems.harmonic_oscillator(A=systems.Switch(-1.0, -4.0, at=12.5), B=1.0,
                                       t_end=25.0, n_times=2000)


@pytest.mark.parametrize("method", ["stlsq", "group"])
def test_windowed_recovers_the_pieces(switched, method):
    model = WindowedSINDy(LINEAR, n_windows=4, method=method)
    model.fit(switched.x, switched.t, x_dot=switched.x_dot, feature_names=["x", "y"])
    assert model.support_.tolist() == [[False, True], [True, False]]
    np.testing.assert_allclose(model.window_coef_[:, 0, 1], [-1, -1, -4, -4], atol=1e-6)
    np.testing.assert_allclose(model.window_coef_[:, 1, 0], 1.0, atol=1e-6)
    coefs = model.coefficients()
    assert coefs.active_terms() == [("x", "y"), ("y", "x")]
    np.testing.assert_allclose(coefs.term("x", "y"), switched.parameters["A"], atol=1e-6)
    assert np.all(coefs.std == 0)


def test_windowed_switch_inside_a_window(switched):
    """Three windows: the switch at 12.5 falls inside the middle one, whose coefficient
    is a least-squares mix of -1 and -4; the outer windows are exact."""
    model = WindowedSINDy(LINEAR, n_windows=3).fit(switched.x, switched.t,
                                                   x_dot=switched.x_dot,
                                                   feature_names=["x", "y"])
    a = model.window_coef_[:, 0, 1]
    np.testing.assert_allclose(a[[0, 2]], [-1.0, -4.0], atol=1e-6)
    assert -4.0 < a[1] < -1.0


def test_windowed_default_windows_and_interpolation(switched):
    """With noise and the default window count the pieces are still found; linear
    interpolation joins window centres."""
    noisy = systems.harmonic_oscillator(A=systems.Switch(-1.0, -4.0, at=12.5), B=1.0,
                                        t_end=25.0, n_times=2000, noise=0.01, seed=1)
    model = WindowedSINDy(ps.PolynomialLibrary(degree=2)).fit(noisy.x, noisy.t,
                                                             feature_names=["x", "y"])
    assert model.n_windows_ in model.cv_errors_ and model.n_windows_ >= 2
    a = model.coefficients().term("x", "y")
    truth = noisy.parameters["A"]
    assert 1 - np.sum((a - truth) ** 2) / np.sum((truth - truth.mean()) ** 2) > 0.95
    assert abs(model.coefficients().switch_times(terms=[("x", "y")])[0] - 12.5) < 0.5
    lin = WindowedSINDy(LINEAR, n_windows=2, interpolation="linear").fit(
        switched.x, switched.t, x_dot=switched.x_dot, feature_names=["x", "y"])
    a = lin.coefficients().term("x", "y")
    assert a[0] == pytest.approx(-1.0) and a[-1] == pytest.approx(-4.0)
    assert a[1000] == pytest.approx(-2.5, abs=0.01)  # halfway between the centres


@pytest.mark.parametrize("kw, fit_kw, match", [
    ({"method": "lasso"}, {}, "method must be one of"),
    ({"interpolation": "cubic"}, {}, "interpolation must be one of"),
    ({"threshold": -1.0}, {}, "threshold"),
    ({"n_windows": 500}, {}, "n_windows=500 leaves 4 samples per window"),
    ({}, {"x_dot": np.zeros((2000, 3))}, "x_dot must have the shape of x"),
])
def test_windowed_errors(switched, kw, fit_kw, match):
    with pytest.raises(ValueError, match=match):
        WindowedSINDy(LINEAR, **kw).fit(switched.x, switched.t, **fit_kw)


def test_windowed_input_errors(switched):
    with pytest.raises(ValueError, match="fits one trajectory, a 2-D array of shape "
                                         "\\(n_times, n_states\\); got a list of 2 arrays"):
        WindowedSINDy(LINEAR).fit([switched.x, switched.x], switched.t)
    with pytest.raises(RuntimeError, match="not fitted"):
        WindowedSINDy(LINEAR).coefficients()
    with pytest.raises(ValueError, match="need at least 40 samples to choose"):
        WindowedSINDy(LINEAR).fit(switched.x[:30], switched.t[:30])


def piecewise_affine(seed, n=1500, dt=0.02):
    """A 2-D spiral sink whose centre jumps between (2, 1) and (-2, -1) at t = 7.5, 15,
    22.5, driven by weak process noise (SLDS's own model class) and observed with noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    switches = np.array([7.5, 15.0, 22.5])
    labels = np.searchsorted(switches, t, side="right") % 2
    centres = np.array([[2.0, 1.0], [-2.0, -1.0]])
    rotation = np.array([[-0.5, -2.0], [2.0, -0.5]])
    x = np.zeros((n, 2))
    x[0] = centres[0]
    for k in range(1, n):
        drift = rotation @ (x[k - 1] - centres[labels[k - 1]])
        x[k] = x[k - 1] + dt * drift + np.sqrt(dt) * 0.3 * rng.normal(size=2)
    return t, x + 0.01 * rng.normal(size=x.shape), labels, switches


@needs_ssm
@pytest.mark.parametrize("method", ["slds", "rslds", "arhmm"])
def test_switching_lds_recovers_the_pieces(method):
    """Three switches between two affine regimes: every switch within 0.1 time units
    (5 samples), >= 99% of the samples labelled right, repeatable with a seed."""
    t, x, labels, switches = piecewise_affine(seed=1)
    seg = switching_lds(x, t, method=method, n_iter=50)
    assert isinstance(seg, Segmentation) and seg.n_states == 2
    assert seg.switch_times.size == 3
    assert switch_time_errors(seg.switch_times, switches).max() < 0.1
    assert seg.accuracy(labels) >= 0.99
    again = switching_lds(x, t, method=method, n_iter=50)
    assert np.array_equal(seg.labels, again.labels)


def test_switching_lds_errors(switched):
    with pytest.raises(ValueError, match="method must be one of"):
        switching_lds(switched.x, switched.t, method="hmm")
    with pytest.raises(ValueError, match="n_states"):
        switching_lds(switched.x, switched.t, n_states=0)
    with pytest.raises(ValueError, match="segments one trajectory, a 2-D array"):
        switching_lds([switched.x], switched.t)
    seg = Segmentation("slds", switched.t, np.zeros(2000, dtype=int), 2, 0.0)
    with pytest.raises(ValueError, match="true_labels must have shape \\(2000,\\)"):
        seg.accuracy(np.zeros(10))
    assert np.isinf(switch_time_errors([], [1.0, 2.0])).all()
    # more states found than true classes: the best one-to-one matching
    three = Segmentation("slds", np.arange(6.0), np.array([0, 0, 1, 1, 2, 2]), 3, 0.0)
    assert three.accuracy([0, 0, 1, 1, 1, 1]) == pytest.approx(4 / 6)


@needs_ssm
def test_a_nested_list_is_one_trajectory(switched):
    nested = switching_lds(switched.x[::10].tolist(), switched.t[::10], n_iter=2)
    assert nested.labels.shape == (200,)


def test_missing_ssm_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ssm", None)
    with pytest.raises(ImportError, match="--no-build-isolation ssm==0.0.1"):
        import_ssm()
