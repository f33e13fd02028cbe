"""The synthetic systems: exact derivatives, coefficient shapes, truth layout."""

import numpy as np
import pytest

from latentsindy import systems


@pytest.mark.parametrize("make", [
    lambda: systems.harmonic_oscillator(A=systems.Sigmoid(-1.0, -4.0, at=5.0), n_times=4000),
    lambda: systems.lorenz(sigma=systems.Sinusoid(10.0, 2.0, 0.1), n_times=8000, t_end=5.0),
    lambda: systems.lotka_volterra(n_times=4000),
], ids=["oscillator", "lorenz", "lotka_volterra"])
def test_derivatives_are_exact(make):
    """x_dot agrees with a 4th-order central difference of x_clean (error O(dt^4))."""
    d = make()
    x, dt = d.x_clean, d.dt
    fd = (-x[4:] + 8 * x[3:-1] - 8 * x[1:-3] + x[:-4]) / (12 * dt)
    np.testing.assert_allclose(fd, d.x_dot[2:-2], rtol=0, atol=1e-5 * np.abs(d.x_dot).max())


def test_true_coefficients_layout():
    d = systems.harmonic_oscillator(A=-2.0, B=3.0, n_times=50)
    truth = d.true_coefficients(["x", "y"], ["1", "x", "y"])
    assert truth.shape == (50, 2, 3)
    np.testing.assert_array_equal(truth[:, 0], np.tile([0.0, 0.0, -2.0], (50, 1)))
    np.testing.assert_array_equal(truth[:, 1], np.tile([0.0, 3.0, 0.0], (50, 1)))
    with pytest.raises(ValueError, match=r"not among feature_names=\['1', 'x'\]"):
        d.true_coefficients(["x", "y"], ["1", "x"])


def test_coefficient_shapes():
    t = np.array([0.0, 1.0, 2.0, 3.0])
    np.testing.assert_array_equal(systems.Switch(1.0, 2.0, at=1.5)(t), [1, 1, 2, 2])
    np.testing.assert_array_equal(systems.Switches((1.0, 2.0, 3.0), (0.5, 2.5))(t), [1, 2, 2, 3])
    assert systems.Sigmoid(0.0, 1.0, at=1.0, sharpness=5.0)(1.0) == pytest.approx(0.5)
    assert systems.Sinusoid(1.0, 2.0, 0.25)(1.0) == pytest.approx(3.0)
    np.testing.assert_allclose(systems.FourierSeries(1.0, (2.0,), (0.25,))(t),
                               systems.Sinusoid(1.0, 2.0, 0.25)(t))


def test_noise_is_relative_to_each_state():
    d = systems.harmonic_oscillator(A=-100.0, B=1.0, n_times=2000, noise=0.05)
    rel = (d.x - d.x_clean).std(axis=0) / d.x_clean.std(axis=0)
    np.testing.assert_allclose(rel, 0.05, rtol=0.1)


def test_switches_validation():
    with pytest.raises(ValueError, match="one more value than switch times"):
        systems.Switches((1.0, 2.0), (0.5, 1.0))
    with pytest.raises(ValueError, match="must increase strictly"):
        systems.Switches((1.0, 2.0, 3.0), (1.0, 0.5))


def test_bad_coefficient_type():
    with pytest.raises(TypeError, match="A must be a number or a callable"):
        systems.harmonic_oscillator(A="fast")
