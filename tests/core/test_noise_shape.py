"""Noise that follows the signal (counts) is read at its root-mean-square level; white
noise and sharp features of the signal are left as they were."""

import numpy as np
import pytest

from latentsindy._core.derivatives import noise_level
from latentsindy._core.noise_shape import level_factor, level_profile

T = np.linspace(0.0, 40.0, 2000)


def _wave():
    """A positive signal spanning two orders of magnitude (an epidemic-like wave)."""
    return 1.0 + 200.0 * np.exp(-((T - 20.0) / 6.0) ** 2)


def test_counts_are_read_at_their_root_mean_square_level():
    """Poisson counts: the variance is the mean, so the median noise level is that of
    the quiet tails; the profile's root-mean-square is the ratio of the true RMS level
    to it (within 10%), and it grows as the square root of the level."""
    rng = np.random.default_rng(0)
    mean = _wave()
    counts = rng.poisson(mean).astype(float)[:, None]
    rms = float(np.sqrt(mean.mean()))
    median = noise_level(counts)[0]
    assert median < 0.85 * rms
    assert level_factor(counts)[0] == pytest.approx(rms / median, rel=0.1)
    profile = level_profile(counts)[0][:, 0] * median
    top = np.argmax(mean)
    assert profile[top] == pytest.approx(np.sqrt(mean[top]), rel=0.15)


@pytest.mark.parametrize("seed", range(3))
def test_white_noise_is_left_as_it_was(seed):
    rng = np.random.default_rng(seed)
    x = np.column_stack([_wave(), np.sin(T)]) + rng.standard_normal((len(T), 2))
    assert np.array_equal(level_factor(x), np.ones(2))


def test_a_sharp_feature_at_the_highest_level_is_not_noise():
    """Narrow pulses (a spiking neuron) at the signal's top: the 4th differences grow
    there with the signal, not with noise, and the 6th differences disagree."""
    rng = np.random.default_rng(1)
    pulses = sum(np.exp(-((T - c) / 0.06) ** 2) for c in np.arange(2.0, 40.0, 3.0))
    x = (10.0 * pulses + 0.01 * rng.standard_normal(len(T)))[:, None]
    assert level_factor(x)[0] == 1.0


def test_short_recordings_are_not_corrected():
    rng = np.random.default_rng(2)
    counts = rng.poisson(_wave()[:200]).astype(float)[:, None]
    assert level_factor(counts)[0] == 1.0
    assert level_factor([counts[:100], counts[100:]])[0] == 1.0
    assert all(np.all(p == 1.0) for p in level_profile([counts[:100], counts[100:]]))
