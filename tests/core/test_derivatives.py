"""Derivatives and noise levels on the actual sample times, against analytic truth."""

import numpy as np
import pytest
from scipy.signal import savgol_coeffs

from latentsindy._core import local_fits
from latentsindy._core.derivatives import (
    _POLYORDER,
    AdaptiveSavitzkyGolay,
    _edge_profile,
    _savgol_derivative,
    measurement_noise,
    noise_level,
    rate,
    window_capped,
)


def random_times(n, t_end=2 * np.pi, seed=0):
    return np.sort(np.random.default_rng(seed).uniform(0.0, t_end, n))


def test_uniform_times_take_the_grid_path():
    t = np.arange(300) * 0.01
    assert local_fits.is_uniform(t) and local_fits.positions(t) is None
    assert not local_fits.is_uniform(random_times(300))


def test_local_fit_is_exact_for_cubics_on_any_times():
    """A cubic is reproduced exactly (value and slope) by the order-3 local fits."""
    t = random_times(200)
    x = (1.0 - 2.0 * t + 0.5 * t**2 - 0.1 * t**3)[:, None]
    values, gain = local_fits.fit(x, t, 9, 0)
    slopes, _ = local_fits.fit(x, t, 9, 1, edge=5)
    np.testing.assert_allclose(values, x, atol=1e-9)
    np.testing.assert_allclose(slopes[:, 0], -2.0 + t - 0.3 * t**2, atol=1e-8)
    assert np.all(gain > 0) and np.all(gain <= 1.0 + 1e-12)  # a fit averages: gain <= 1


def test_irregular_derivative_converges_at_third_order():
    """Noise-free sin on random times: the median derivative error falls by at least
    2^2.5 when the number of samples doubles (third order on uneven windows; the median,
    because the largest error sits wherever random times happen to cluster)."""
    errors = []
    for n in (200, 400, 800, 1600):
        t = random_times(n, seed=n)
        d = AdaptiveSavitzkyGolay()(np.sin(t)[:, None], t)[:, 0]
        errors.append(np.median(np.abs(d - np.cos(t))))
    assert errors[0] < 1e-5
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(rates > 2.5), (errors, rates)


def test_noise_level_on_irregular_times_is_the_true_sigma():
    """White noise of std 0.01 on a smooth signal at random times: the estimate is
    within 10% of the truth (2000 samples: the MAD's own spread is about 2%)."""
    t = random_times(2000, t_end=20.0, seed=3)
    rng = np.random.default_rng(4)
    x = np.column_stack([np.sin(t), np.cos(0.5 * t)]) + 0.01 * rng.standard_normal((2000, 2))
    np.testing.assert_allclose(noise_level(x, t), 0.01, rtol=0.10)


@pytest.mark.parametrize("irregular", [False, True])
def test_noise_gain_matches_the_measured_derivative_noise(irregular):
    """The reported gain times sigma^2 is the variance the differentiator passes from
    white noise into its derivative (away from the ends), within 10%."""
    n = 20000
    t = random_times(n, t_end=200.0, seed=5) if irregular else np.linspace(0, 200.0, n)
    noise = 0.02 * np.random.default_rng(6).standard_normal((n, 1))
    method = AdaptiveSavitzkyGolay(max_window=9)
    d = method(noise, t)
    interior = slice(50, -50)
    predicted = 0.02**2 * np.mean((method.noise_gain_ * method.noise_profile_)[interior, 0])
    np.testing.assert_allclose(np.var(d[interior, 0]), predicted, rtol=0.10)


def test_pooled_noise_level_counts_every_sample_once():
    """Segments of one instrument (std 0.01), one of 4000 samples and two of 60 (at
    random times): pooled, the short ones weigh by their samples, so the estimate stays
    within 0.5% of the long one's (the mean of the three levels is 1.9% off: the short
    ones read 0.0070 and 0.0125); one segment gives its own level exactly."""
    rng = np.random.default_rng(7)
    long_t = np.linspace(0, 40, 4000)
    short = [random_times(60, t_end=1.0, seed=s) for s in (8, 9)]
    times = [long_t, *short]
    xs = [np.sin(t)[:, None] + 0.01 * rng.standard_normal((len(t), 1)) for t in times]
    long_level = noise_level(xs[0], long_t)
    np.testing.assert_allclose(noise_level(xs, times), long_level, rtol=0.005)
    np.testing.assert_allclose(long_level, 0.01, rtol=0.05)
    assert noise_level(xs[:1], times[:1]) == noise_level(xs[0], long_t)


def test_given_noise_level_sets_the_window():
    """A known noise level replaces the estimate: the window is the one the estimate
    would give when it is right, and an underestimate by a third shrinks it."""
    t = np.linspace(0, 10, 1000)
    x = np.sin(t)[:, None] + 0.01 * np.random.default_rng(10).standard_normal((1000, 1))
    own = AdaptiveSavitzkyGolay()
    own(x, t)
    given = AdaptiveSavitzkyGolay(noise_std=float(noise_level(x, t)[0]))
    given(x, t)
    low = AdaptiveSavitzkyGolay(noise_std=0.0067)
    low(x, t)
    assert given.windows_ == own.windows_ and low.windows_[0] < own.windows_[0] / 2


def test_bad_noise_std_is_refused():
    with pytest.raises(ValueError, match=r"noise_std must be one non-negative finite number "
                                         r"or one per state \(2\); got \[0.1, 0.1, 0.1\]"):
        AdaptiveSavitzkyGolay(noise_std=[0.1, 0.1, 0.1])(np.zeros((50, 2)), 0.1)


def test_window_capped_says_when_length_limited_the_window():
    """Noise-free data want the narrowest window (not capped); a smooth noisy series of
    60 samples wants more than its cap of 11 allows."""
    t = np.linspace(0, 1, 60)
    noisy = (t + 0.05 * np.random.default_rng(11).standard_normal(60))[:, None]
    m = AdaptiveSavitzkyGolay()
    m(noisy, t)
    assert m.windows_ == [11] and window_capped(11, 60)
    assert not window_capped(5, 1000)


def test_measurement_noise_sees_through_sparse_sampling():
    """A sinusoid and its harmonic sampled 12 times per cycle with 1% white noise:
    their 4th differences (the signal, not noise) make noise_level read four times the
    truth (0.041); measurement_noise, from higher orders, within 25% (0.011). Sampled densely
    (200 per cycle) both read the same number."""
    rng = np.random.default_rng(3)
    for per_cycle, tolerance in ((12, 0.25), (200, 0.1)):
        t = np.arange(120 if per_cycle == 12 else 2000) * (2 * np.pi / per_cycle)
        x = (np.sin(t) + np.sin(2 * t + 1) / 3)[:, None]
        noisy = x + 0.01 * rng.standard_normal(x.shape)
        np.testing.assert_allclose(measurement_noise(noisy, t), 0.01, rtol=tolerance)
        if per_cycle == 12:
            assert noise_level(noisy, t)[0] > 3 * 0.01
        else:
            assert measurement_noise(noisy, t) == noise_level(noisy, t)


@pytest.mark.parametrize("irregular", [False, True])
def test_the_rate_alone_is_the_methods_derivative_to_the_bit(irregular):
    """``rate`` leaves out the noise diagnostics, not any of the derivative's work: the
    same derivative and windows as ``AdaptiveSavitzkyGolay``, to the bit."""
    rng = np.random.default_rng(2)
    t = (np.sort(rng.uniform(0, 20, 600)) if irregular else np.linspace(0, 20, 600))
    x = np.column_stack([np.sin(t), np.cos(0.3 * t) ** 3]) + 0.01 * rng.normal(size=(600, 2))
    method = AdaptiveSavitzkyGolay()
    want = method(x, t)
    got, windows = rate(x, t)
    assert np.array_equal(got, want) and windows == method.windows_
    assert min(windows) > 5  # noisy data: windows wider than the smallest


@pytest.mark.parametrize(("n", "window"), [(7, 7), (30, 9), (61, 21), (200, 41), (301, 81),
                                           (400, 31), (1000, 101)])
def test_noise_gain_along_the_series_is_every_impulses_response(n, window):
    """The derivative's white-noise gain per sample (``noise_profile_``'s shape) is the
    sum of squares of its response to a unit impulse at every sample (to rounding), and
    to the bit what differentiating the first ``2 window`` impulses as a series of all
    ``n`` samples gives: the profile differentiates them as ``3 window`` samples."""
    dt = 0.37
    got = _edge_profile(n, window, dt)
    response = _savgol_derivative(np.eye(n), window, dt)
    assert np.allclose(got, np.sum(response ** 2, axis=1), rtol=1e-12, atol=0)
    assert got[0] > 1.5 * got[n // 2]
    k = min(n, 2 * window)  # the whole-series formulation, as the profile was made
    head = np.sum(_savgol_derivative(np.eye(n)[:, :k], window, dt)[:window] ** 2, axis=1)
    interior = np.sum(savgol_coeffs(window, _POLYORDER, deriv=1, delta=dt) ** 2)
    want = np.full(n, interior)
    want[:window] = np.maximum(head, interior)
    want[n - window:] = np.maximum(want[n - window:], head[::-1][-min(window, n):])
    assert np.array_equal(got, want)
