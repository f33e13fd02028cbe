"""The coefficient figure: mean, band, truth and switch lines."""

import matplotlib
import numpy as np
import pytest

from latentsindy import CoefficientSeries

matplotlib.use("Agg")


def test_coefficient_plot_marks_switches_and_truth(tmp_path):
    """A coefficient that steps from 1 to 2 at t = 5: its panel shows the mean, the
    band, the truth and one switch line at 5 (within a sample spacing of the grid)."""
    t = np.linspace(0.0, 10.0, 501)
    step = np.where(t < 5.0, 1.0, 2.0)
    samples = np.stack([step + 0.01 * k for k in range(-2, 3)])[:, :, None, None]
    series = CoefficientSeries.from_samples(t, samples.mean(axis=0), samples, ["x"], ["y"],
                                            np.ones((1, 1), bool), np.ones((1, 1), bool))
    fig = series.plot(truth={("x", "y"): step}, path=tmp_path / "c.png")
    (ax,) = fig.axes
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert set(lines) == {"posterior mean", "truth", "switch"}
    assert abs(lines["switch"].get_xdata()[0] - 5.0) <= 0.05
    assert (tmp_path / "c.png").exists()
    with pytest.raises(KeyError, match="Unknown feature 'z'"):
        series.plot(terms=[("x", "z")])


def test_the_figure_draws_the_band_and_says_the_doubts():
    t = np.linspace(0.0, 10.0, 101)
    mean = np.sin(t)[:, None, None]
    series = CoefficientSeries.from_samples(
        t, mean, mean[None], ["x"], ["y"], np.ones((1, 1), bool), np.ones((1, 1), bool),
        lower=mean - 0.3, upper=mean + 0.5, doubts=["dx/dt: the structure is uncertain"])
    np.testing.assert_allclose(series.half_width, 0.4)
    fig = series.plot()
    (ax,) = fig.axes
    band = ax.collections[0].get_paths()[0].vertices[:, 1]
    assert band.min() == pytest.approx(-1.3, abs=0.02) and band.max() == pytest.approx(
        1.5, abs=0.02)
    assert "the structure is uncertain" in fig._suptitle.get_text()
    assert "DOUBTS" in series.summary()


def test_a_series_made_from_samples_it_owns_is_the_copying_ones():
    """The estimator gives its own samples away (frozen in place, not copied: 100 MB
    on 20,000 times); the series is the one ``from_samples`` makes from a copy, and
    ``from_samples`` leaves the caller's arrays writable."""
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 10.0, 301)
    samples = rng.normal(size=(8, 301, 2, 3))
    mean = samples.mean(axis=0)
    masks = (np.ones((2, 3), bool), np.ones((2, 3), bool))
    copied = CoefficientSeries.from_samples(t, mean, samples, ["x", "y"], ["1", "x", "y"],
                                            *masks)
    assert samples.flags.writeable and not copied.samples.flags.writeable
    own = samples.copy()
    given = CoefficientSeries._of(t, mean, own, ["x", "y"], ["1", "x", "y"], *masks, None,
                                  None, (), std=own.std(axis=0), own=True)
    assert given.samples is own and not own.flags.writeable
    for name in ("times", "mean", "std", "samples", "noise_across_samples",
                 "noise_around_smooth_mean", "lower", "upper"):
        assert np.array_equal(getattr(given, name), getattr(copied, name)), name


@pytest.mark.parametrize("time_inner", [False, True])
@pytest.mark.parametrize("shape", [(64, 2000, 1, 9), (8, 600, 2, 10), (3, 50, 1, 2),
                                   (5, 300, 1, 1), (4, 1, 2, 3)])
def test_noise_around_the_smooth_mean_is_numpys_std_to_the_bit(shape, time_inner):
    """The second noise estimate (std over time of each sample about its smoothed self,
    averaged over samples) is numpy's ``std(axis=1)`` of the difference in every digit,
    for one term or many, samples laid out in C order or with time innermost (as the
    generator's series come); white noise of level 0.3 about a slow curve reads 0.3."""
    from scipy.ndimage import uniform_filter1d

    from latentsindy._stage_one.coefficients import _spread_around

    rng = np.random.default_rng(sum(shape))
    t = np.linspace(0.0, 1.0, shape[1])
    curve = np.sin(2 * np.pi * t)[None, :, None, None]
    samples = curve + 0.3 * rng.standard_normal(shape)
    if time_inner:
        samples = np.moveaxis(np.ascontiguousarray(np.moveaxis(samples, 1, -1)), -1, 1)
    series = CoefficientSeries.from_samples(t, samples.mean(axis=0), samples,
                                            [f"s{i}" for i in range(shape[2])],
                                            [f"f{j}" for j in range(shape[3])],
                                            np.ones(shape[2:], bool), np.ones(shape[2:], bool))
    width = max(5, (shape[1] // 50) | 1)
    smooth = uniform_filter1d(samples, size=width, axis=1, mode="nearest")
    want = (samples - smooth).std(axis=1)
    assert np.array_equal(_spread_around(samples, smooth), want)
    assert np.array_equal(series.noise_around_smooth_mean, want.mean(axis=0))
    if shape[1] >= 600:  # the smoother's own share of the noise is small
        np.testing.assert_allclose(series.noise_around_smooth_mean, 0.3, rtol=0.1)


@pytest.mark.parametrize("shape", [(6, 300, 1, 9), (4, 200, 2, 3)])
def test_a_difference_with_time_innermost_is_left_to_numpy(shape):
    """Where the samples' difference from their smoothed selves has time as its inner
    axis numpy sums along it pairwise, which the compiled pass does not: such a
    difference is numpy's std, to the bit (the generator's series come with time
    innermost, but their smoothed copy, and so the difference, in C order)."""
    from latentsindy._stage_one.coefficients import _spread_around

    rng = np.random.default_rng(3)

    def time_inner(a):
        return np.moveaxis(np.ascontiguousarray(np.moveaxis(a, 1, -1)), -1, 1)

    samples = time_inner(rng.standard_normal(shape) * 1e3 + rng.standard_normal(shape))
    smooth = time_inner(0.5 * rng.standard_normal(shape))
    assert not (samples - smooth).flags.c_contiguous
    want = (samples - smooth).std(axis=1)
    assert np.array_equal(_spread_around(samples, smooth), want)
