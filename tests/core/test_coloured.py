"""Coloured (AR(1)) measurement noise: its reading from the data, and the variance gain
of a linear filter on it, against analytic values and simulated noise."""

import numpy as np
import pytest
from scipy.signal import savgol_coeffs

from latentsindy._core import coloured
from latentsindy._core.coloured import HIGH, ar1_gain, ar1_noise
from latentsindy._core.derivatives import AdaptiveSavitzkyGolay, state_noise


def _ar1(rng, n, cols, phi):
    e = np.zeros((n, cols))
    e[0] = rng.standard_normal(cols)
    for k in range(1, n):
        e[k] = phi * e[k - 1] + np.sqrt(1 - phi**2) * rng.standard_normal(cols)
    return e


def _oscillations(n):
    t = np.arange(n, dtype=float)
    return np.column_stack([np.sin(2 * np.pi * t / 100),
                            np.cos(2 * np.pi * t / 130) + 0.3 * np.sin(2 * np.pi * t / 47)])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_high_correlation_under_an_oscillation_is_read_with_the_signal_taken_out(seed):
    """AR(1) 0.9 noise (2% of each state's std) on oscillations of 47-130 samples per
    cycle: noise alone reads the correlation at the grid's top (0.98 > HIGH, or misses
    the curve), which would make it white and its level 4 times too low. With the
    signal's share taken out it reads 0.7-0.95, the level 0.55-1.35 of the truth
    (the faster signal of the second state biases both low)."""
    rng = np.random.default_rng(seed)
    x = _oscillations(2000)
    sigma = 0.02 * x.std(axis=0)
    y = x + sigma * _ar1(rng, 2000, 2, 0.9)
    ms = np.arange(1, coloured.M + 1)
    for j in range(2):
        v = np.array([coloured._robust_var(coloured._dilated(y[:, j], m)) for m in ms])
        err, _, phi_alone = coloured._ar1_fit(v, ms)
        assert phi_alone > HIGH or err > coloured.FIT
    level, phi = ar1_noise(y)
    assert 0.8 <= phi[0] <= 0.95 and 0.65 <= level[0] / sigma[0] <= 1.35
    assert 0.65 <= phi[1] <= 0.95 and 0.5 <= level[1] / sigma[1] <= 1.35
    sigma_read, phi_read = state_noise(y)
    np.testing.assert_array_equal(phi_read, phi)
    np.testing.assert_allclose(sigma_read, level)


@pytest.mark.parametrize("noise", [0.0, 0.01, 0.05, 0.1])
def test_white_noise_and_clean_oscillations_read_white(noise):
    """No reading (noise alone, or with the signal's share on 8 or 12 spacings) takes
    white noise of any level, or none, for coloured noise."""
    rng = np.random.default_rng(3)
    x = _oscillations(2000)
    y = x + noise * x.std(axis=0) * rng.standard_normal(x.shape)
    level, phi = ar1_noise(y)
    assert level == [None, None] and np.all(phi == 0)


@pytest.mark.parametrize("phi", [0.0, 0.5, 0.9])
def test_ar1_gain_is_exact(phi):
    """A difference's gain is 2 - 2 phi; a Savitzky-Golay derivative's matches its
    variance on simulated AR(1) noise (200,000 samples: within 3%)."""
    assert ar1_gain([1.0, -1.0], phi) == pytest.approx(2 - 2 * phi, abs=1e-12)
    c = savgol_coeffs(21, 3, deriv=1)
    e = _ar1(np.random.default_rng(4), 200_000, 1, phi)[:, 0]
    filtered = np.convolve(e, c, mode="valid")
    assert np.var(filtered) == pytest.approx(ar1_gain(c, phi), rel=0.03)


def test_the_default_differentiator_reads_coloured_noise():
    """Its window is chosen against the noise's marginal level (several times the white
    reading), and its derivative's noise gain is the AR(1) one."""
    rng = np.random.default_rng(0)
    x = _oscillations(2000)[:, :1]
    y = x + 0.02 * x.std() * _ar1(rng, 2000, 1, 0.9)
    method = AdaptiveSavitzkyGolay()
    method(y, 1.0)
    white = AdaptiveSavitzkyGolay(noise_std=state_noise(y)[0] / 4, noise_correlation=0.0)
    white(y, 1.0)
    assert 0.8 <= method.noise_correlation_[0] <= 0.95
    assert method.windows_[0] > white.windows_[0]
    c = savgol_coeffs(method.windows_[0], 3, deriv=1)
    assert method.noise_gain_[0] == pytest.approx(ar1_gain(c, method.noise_correlation_[0]))


def test_a_bad_noise_correlation_is_an_error():
    with pytest.raises(ValueError, match=r"noise_correlation must be one number in \[0, 1\) "
                                         r"or one per state \(2\); got 1.0"):
        AdaptiveSavitzkyGolay(noise_std=0.1, noise_correlation=1.0)(np.ones((50, 2)), 0.1)


def _signal_fit_by_nnls(v, ms):
    """The reading with a signal's share, one non-negative least squares per
    correlation of the grid (the definition the closed form must match)."""
    from scipy.optimize import nnls

    best = (np.inf, 0.0, 0.0)
    for p in coloured._PHIS:
        design = np.stack([np.polyval(coloured._G[::-1], p**ms), (ms / ms[-1]) ** 8], axis=1)
        coef = nnls(design / v[:, None], np.ones(len(v)))[0]
        if coef[0] > 0:
            err = float(np.sum(np.log(v / (design @ coef)) ** 2))
            if err < best[0]:
                best = (err, float(np.log(coef[0])), float(p))
    return best


@pytest.mark.parametrize("v", [
    np.r_[70.0 * np.ones(4), 70.0 * (1 + (np.arange(5, 13) / 6.0) ** 8)],  # noise + signal
    np.polyval(coloured._G[::-1], 0.9 ** np.arange(1, 13)),  # AR(1) alone
    1e-160 * np.polyval(coloured._G[::-1], 0.5 ** np.arange(1, 13)),  # tiny
    0.07 + (np.arange(1, 13) / 12.0) ** 8,  # mostly signal
    np.r_[4.3e-31, 7.6e-4 * (np.arange(2, 13) / 2.0) ** 2],  # a near-exact series' spread
])
def test_closed_form_signal_fit_is_the_nonnegative_least_squares(v):
    """The two-coefficient reading, solved in closed form for every correlation at
    once, is the per-correlation NNLS one (same correlation, misfit and level to 1e-9),
    and a spread over 30 decades raises no warning (warnings are errors here). (Where
    both fit exactly, as on a signal without noise, every correlation ties to rounding
    and either may be read; both then read the noise as white.)"""
    ms = np.arange(1, 13)
    err, level, phi = coloured._ar1_signal_fit(v, ms)
    ref = _signal_fit_by_nnls(v, ms)
    assert phi == ref[2]
    assert (err, level) == pytest.approx(ref[:2], rel=1e-9, abs=1e-12)


def test_a_reading_is_kept_by_content_and_given_out_as_a_copy():
    """The same recordings read again (a copy, or split the same way) give the first
    reading without computing it again; what is returned can be changed without
    changing what is kept; another recording, or the same one irregularly sampled, is
    read afresh."""
    rng = np.random.default_rng(3)
    x = _oscillations(2000) + 0.02 * _ar1(rng, 2000, 2, 0.9)
    first = ar1_noise(x)
    assert first[1][0] > 0  # read as coloured: a reading worth keeping
    kept = len(coloured._READ)
    first[0][0], first[1][0] = None, -1.0  # the caller's copies
    again = ar1_noise(x.copy())
    assert len(coloured._READ) == kept
    coloured._READ.clear()
    fresh = ar1_noise(x)
    assert again[0] == fresh[0] and np.array_equal(again[1], fresh[1])
    ar1_noise(x[:-1])
    assert len(coloured._READ) == 2
    irregular = np.sort(rng.uniform(0, 100, 2000))
    assert np.array_equal(ar1_noise(x, irregular)[1], np.zeros(2))  # white: not uniform
