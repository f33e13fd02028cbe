"""Isolated spikes are discounted and listed; noise and sharp dynamics are left alone."""

import numpy as np
import pytest

from latentsindy._core import recordings
from latentsindy._core.spikes import LOCAL, WINDOW, _local_spread, discount


def curve(t):
    return np.column_stack([np.sin(t) + 0.3 * np.sin(3 * t), np.cos(0.7 * t)])


def test_spikes_of_ten_noise_levels_are_found_and_replaced():
    """0.5% of 2000 samples (10) hit by +-10 noise levels in one state: all 10 found,
    nothing else, and each replaced within 4 noise levels of the true curve."""
    rng = np.random.default_rng(0)
    t = np.linspace(0, 40, 2000)
    clean = curve(t)
    x = clean + 0.01 * rng.standard_normal(clean.shape)
    hit = rng.choice(np.arange(5, 1995), 10, replace=False)
    x[hit, 0] += 0.1 * rng.choice([-1.0, 1.0], 10)
    mask, cleaned = discount(x, t)
    assert set(np.flatnonzero(mask)) == set(hit)
    assert np.max(np.abs(cleaned[hit, 0] - clean[hit, 0])) < 0.04
    np.testing.assert_array_equal(cleaned[~mask], x[~mask])


@pytest.mark.parametrize("gap, signs", [(1, (1, -1)), (2, (1, 1)), (2, (1, -1)),
                                         (3, (-1, -1)), (4, (1, -1))])
def test_spikes_close_together_are_found_as_a_pair(gap, signs):
    """Two spikes within four samples move each other's prediction (the one between two
    same-signed spikes looks like a dip): both found, nothing else, each replaced within
    4 noise levels of the curve."""
    rng = np.random.default_rng(5)
    t = np.linspace(0, 40, 2000)
    clean = curve(t)
    x = clean + 0.01 * rng.standard_normal(clean.shape)
    hit = [700, 700 + gap]
    x[hit, 0] += 0.1 * np.array(signs)
    mask, cleaned = discount(x, t)
    assert set(np.flatnonzero(mask)) == set(hit)
    assert np.max(np.abs(cleaned[hit, 0] - clean[hit, 0])) < 0.04


def test_two_adjacent_samples_off_to_one_side_are_kept():
    """Two neighbouring samples off the curve in the same direction are a feature two
    samples wide, not two spikes."""
    rng = np.random.default_rng(6)
    t = np.linspace(0, 40, 2000)
    x = curve(t) + 0.01 * rng.standard_normal((2000, 2))
    x[[700, 701], 0] += 0.1
    assert not discount(x, t)[0].any()


@pytest.mark.parametrize("noise", [0.0, 0.001, 0.01, 0.1])
def test_white_noise_is_not_a_spike(noise):
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0, 40, 3000))  # irregular times too
    x = curve(t) + noise * rng.standard_normal((3000, 2))
    assert not discount(x, t)[0].any()


def test_sharp_features_of_the_dynamics_are_kept():
    """A relaxation jump over 3 samples and a pulse 2 samples wide at half height (a
    neuron's spike sampled coarsely) sit far off their neighbours' curve, but they are
    not isolated: their neighbours are off it too."""
    t = np.arange(600) * 0.1
    jump = np.tanh((t - 20.0) / 0.1)
    pulse = np.exp(-0.5 * ((t - 40.0) / 0.1) ** 2)
    x = np.column_stack([jump, pulse]) + 1e-3 * np.random.default_rng(2).standard_normal((600, 2))
    assert not discount(x, t)[0].any()


def test_counts_whose_noise_follows_their_level_are_not_spikes():
    rng = np.random.default_rng(3)
    t = np.linspace(0, 30, 2000)
    level = 400 * (1.2 + np.sin(t)) ** 2  # counts from ~16 to ~1900
    x = rng.poisson(level)[:, None].astype(float)
    assert not discount(x, t)[0].any()


def test_split_lists_the_discounted_samples_and_keep_keeps_them():
    rng = np.random.default_rng(4)
    t = np.linspace(0, 40, 1000)
    x = curve(t) + 0.01 * rng.standard_normal((1000, 2))
    x[[100, 600], 1] += 0.2
    segs, _, use = recordings.split(x, t)
    assert use.discounted == ((0, float(t[100])), (0, float(t[600])))
    assert "2 isolated spike(s) discounted (t=4.004, t=24.024)" in use.sentence()
    assert abs(segs[0][100, 1] - x[100, 1]) > 0.15
    segs, _, use = recordings.split(x, t, outliers="keep")
    assert use.discounted == () and np.array_equal(segs[0], x)
    with pytest.raises(ValueError, match=r"outliers must be one of \('discount', 'keep'\); "
                                         r"got 'drop'"):
        recordings.split(x, t, outliers="drop")


@pytest.mark.parametrize("seed", range(4))
def test_local_spread_is_every_windows_median_where_it_stands_out(seed):
    """Only windows where half the samples exceed the bar are sorted; the spread is
    still, sample for sample, the definition's: the median of every window of
    ``WINDOW`` samples where it is over ``LOCAL`` times the whole series', else the
    whole series'. Residuals whose level varies 50-fold (some windows over the bar,
    most not), with ties."""
    rng = np.random.default_rng(seed)
    n = 1500
    r = np.round(3 * rng.standard_normal(n)) / 3 * np.exp(2 * np.sin(np.linspace(0, 9, n)))
    whole = 1.4826 * np.median(np.abs(r))
    windows = np.lib.stride_tricks.sliding_window_view(np.abs(r), WINDOW)
    med = 1.4826 * np.median(windows, axis=1)
    local = np.concatenate([np.full(WINDOW // 2, med[0]), med, np.full(WINDOW // 2, med[-1])])
    want = np.where(local > LOCAL * whole, local, whole)
    assert 0.1 < np.mean(want > whole) < 0.9
    np.testing.assert_array_equal(_local_spread(r), want)


def test_local_spread_at_the_bar_itself():
    """Windows whose median residual sits one rounding step above the bar (1.5 times
    the whole series' spread) read their own spread; at the bar exactly, or with one
    sample short of half over it, the whole series'."""
    n, half = 1200, WINDOW // 2
    r = np.ones(n)
    at = 1.5  # 1.4826 * 1.5 is the bar exactly: not over it
    over = np.nextafter(1.5, 2.0)
    while not 1.4826 * over > LOCAL * 1.4826:  # the first value whose spread is over
        over = np.nextafter(over, 2.0)
    r[200:200 + WINDOW] = over  # one window's worth: its middle window is over
    r[600:600 + WINDOW] = at
    r[900:900 + half] = over  # one short of half of any window
    whole = 1.4826 * np.median(np.abs(r))
    assert whole == 1.4826 and 1.4826 * over > LOCAL * whole >= 1.4826 * at
    spread = _local_spread(r)
    assert spread[200 + half] == 1.4826 * over
    assert np.all(spread[600 - half:600 + WINDOW + half] == whole)
    assert np.all(spread[850:1000] == whole)
    centre = np.arange(n)  # windows centred 200..300 hold 51 or more of the block
    np.testing.assert_array_equal(spread > whole, (centre >= 200) & (centre <= 300))
