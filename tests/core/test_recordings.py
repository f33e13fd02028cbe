"""Recordings as measured: missing rows, gaps, short pieces, and bad input at the boundary."""

import numpy as np
import pysindy as ps
import pytest

from latentsindy import discover_hidden
from latentsindy._core import recordings
from latentsindy.results import DataUse


def series(n=400, seed=0):
    t = np.sort(np.random.default_rng(seed).uniform(0.0, 20.0, n))
    return np.column_stack([np.sin(t), np.cos(t)]), t


def test_random_times_are_never_split():
    """Poisson sample times (100,000 of them, longest step ~12 mean steps) stay whole."""
    t = np.cumsum(np.random.default_rng(1).exponential(1.0, 100_000))
    assert len(recordings.gap_steps(t)) == 0


def test_two_sampling_rates_are_not_a_gap():
    t = np.concatenate([np.arange(300) * 0.01, 3.0 + np.arange(1, 300) * 0.1])
    assert len(recordings.gap_steps(t)) == 0


def test_missing_rows_and_gaps_split_a_recording():
    x, t = series(1000)
    x[100:103] = np.nan  # a few missing rows: irregular sampling, no split
    x[500:600, 1] = np.nan  # a long stretch: a gap
    t[700:] += 50.0  # a jump in time: another gap
    with pytest.warns(UserWarning, match=r"103 of the 1000 rows of x_observed \(10%\) are not "
                                         r"used as measured: 103 have a missing value, 0 lie in"):
        segs, times, use = recordings.split(x, t)
    assert use == DataUse(1, 3, 897, 103, (), ((0, 0, 499), (0, 600, 699), (0, 700, 999)))
    assert [len(s) for s in segs] == [497, 100, 300]
    assert all(np.all(np.isfinite(s)) for s in segs)
    np.testing.assert_array_equal(times[2], t[700:])
    assert "3 segments, 897 samples used (103 rows with missing values dropped)" in use.sentence()


def test_short_pieces_are_dropped_with_a_note():
    x, t = series(400)
    x[12:100] = np.nan  # leaves 12 samples before the gap
    with pytest.warns(UserWarning, match=r"100 of the 400 rows .* 88 have a missing value, "
                                         r"12 lie in segments shorter than 16"):
        segs, _, use = recordings.split(x, t)
    assert len(segs) == 1 and use.segments == 1
    assert len(use.dropped) == 1
    assert "with 12 samples" in use.dropped[0] and "fewer than 16" in use.dropped[0]


def test_several_recordings_of_different_rates():
    a, ta = series(300, seed=1)
    b = a[::3][:90]
    segs, times, use = recordings.split([a, b], [ta, ta[::3][:90]])
    assert (use.recordings, use.segments, use.samples) == (2, 2, 390)


def test_gaps_raise_refuses_missing_values_and_gaps():
    x, t = series(400)
    x[200, 0] = np.nan
    with pytest.raises(ValueError, match=r"1 row\(s\) with a NaN.*row 200.*gaps='raise'"):
        recordings.split(x, t, gaps="raise")
    x, t = series(400)
    t[200:] += 100.0
    with pytest.raises(ValueError, match=r"1 gap\(s\).*gaps='raise'"):
        recordings.split(x, t, gaps="raise")


# ------------------------------------------------ bad input, at discover_hidden's boundary
def discover(x, t=0.1, **kw):
    return discover_hidden(x, ps.PolynomialLibrary(degree=2), t=t, verbose=False, **kw)


def test_unknown_gaps_option():
    with pytest.raises(ValueError, match=r"gaps must be one of \('split', 'raise'\); got 'skip'"):
        discover(series()[0], gaps="skip")


@pytest.mark.parametrize("x, kind", [
    (np.ones((100, 1), dtype=complex), r"complex array \(dtype complex128\).*np.real"),
    (np.ones((100, 1), dtype=bool), r"boolean array \(dtype bool\)"),
    (np.array([[object()]] * 100), r"object array \(dtype object\)"),
    (np.array([["1.0"]] * 100), r"string array \(dtype <U3\)"),
])
def test_non_real_data_are_refused(x, kind):
    with pytest.raises(TypeError, match="x_observed must hold real numbers.*" + kind):
        discover(x)


def test_single_sample():
    with pytest.raises(ValueError, match=r"got shape \(1, 2\): at least 16 samples"):
        discover(np.ones((1, 2)))


def test_shorter_than_a_law_and_its_start_need():
    with pytest.raises(ValueError, match=r"at least 8 samples without a gap.*16 for stage "
                                         r"one.*8 per cycle.*with 7 samples"):
        discover(series()[0][:7])


def test_all_nan_column():
    x = series()[0]
    x[:, 1] = np.nan
    with pytest.raises(ValueError, match=r"state column\(s\) \[1\] with no finite value"):
        discover(x)


@pytest.mark.parametrize("fault, message", [
    ("duplicate", r"strictly increasing; t\[50\]=.* is followed by t\[51\]"),
    ("decreasing", r"strictly increasing; t\[50\]=.* is followed by t\[51\]"),
])
def test_times_must_increase(fault, message):
    x, t = series()
    t[51] = t[50] if fault == "duplicate" else t[50] - 0.01
    with pytest.raises(ValueError, match=message):
        discover(x, t=t)


def test_times_of_a_second_recording_are_named():
    x, t = series()
    bad = t.copy()
    bad[10] = bad[9]
    with pytest.raises(ValueError, match=r"t\[1\]\[9\]=.* is followed by"):
        discover([x, x], t=[t, bad])


def test_datetime_times_are_refused():
    x, _ = series(100)
    t = np.arange(100).astype("datetime64[s]")
    with pytest.raises(TypeError, match="real sample times.*datetime"):
        discover(x, t=t)


def test_rows_all_missing_somewhere():
    """Two states logged alternately: every row misses one, nothing is left."""
    x, t = series(100)
    x[::2, 0] = np.nan
    x[1::2, 1] = np.nan
    with pytest.raises(ValueError, match=r"Every row of x_observed \(100 rows\) has a NaN.*"
                                         "common time grid"):
        recordings.split(x, t)


def test_a_list_of_one_state_recordings_with_their_times():
    a, ta = series(300, seed=1)
    b, tb = series(200, seed=2)
    segs, _, use = recordings.split([a[:, 0], b[:, 0]], [ta, tb])
    assert [s.shape for s in segs] == [(300, 1), (200, 1)]
    assert (use.recordings, use.samples) == (2, 500)


def test_a_ragged_list_of_one_state_recordings_without_their_times():
    a, _ = series(300, seed=1)
    with pytest.raises(ValueError, match=r"list of 2 1-D arrays of different lengths "
                                         r"\[300, 200\].*t as a list"):
        recordings.split([a[:, 0], a[:200, 0]], 0.1)


def test_several_time_arrays_for_one_recording():
    x, t = series(100)
    with pytest.raises(ValueError, match="t is a list of 2 arrays of times but x is one "
                                         "recording"):
        recordings.split(x, [t, t])


@pytest.mark.parametrize("dt", [True, "0.1", 1j])
def test_a_spacing_that_is_not_a_real_number(dt):
    x, _ = series(100)
    with pytest.raises(TypeError, match="sample spacing t must be a positive real number"):
        recordings.split(x, dt)


def test_a_tenth_of_a_recording_unused_is_not_worth_a_warning():
    x, t = series(1000)
    x[100:200] = np.nan  # exactly 10%: the warning starts above it
    segs, _, use = recordings.split(x, t)
    assert use.missing_rows == 100 and sum(len(s) for s in segs) == 900


@pytest.mark.parametrize("where", ["x", "t"])
def test_infinite_values_are_an_error_naming_the_rows(where):
    x, t = series(400)
    if where == "x":
        x[[3, 250], 1] = np.inf
        x[7, 0] = -np.inf
    else:
        t = t.copy()
        t[[3, 7, 250]] = np.inf
    with pytest.raises(ValueError, match=r"x_observed has 3 row\(s\) with an infinite value or "
                                         r"time \(rows 3, 7, 250\)\. .*replace it with NaN"):
        recordings.split(x, t)


def test_infinite_values_of_a_second_recording_are_named():
    x, t = series(400)
    y = x.copy()
    y[np.arange(10, 80, 10), 0] = np.inf
    with pytest.raises(ValueError, match=r"x_observed\[1\] has 7 row\(s\) .*\(rows 10, 20, 30, "
                                         r"40, 50, \.\.\.\)"):
        recordings.split([x, y], [t, t])
