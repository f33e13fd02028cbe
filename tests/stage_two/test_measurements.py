"""Discovery on data as measured: random sample times with gaps and missing rows."""

import numpy as np
import pysindy as ps
import pytest
import sympy as sp

from latentsindy import discover_hidden, systems
from latentsindy._stage_two.context_build import knot_spacing as _knot_spacing
from latentsindy._stage_two.discover import _varying


@pytest.fixture(scope="module")
def irregular_with_gaps():
    """Prey-only Lotka-Volterra at 1500 sorted random times over 40 time units, 1% noise,
    a stretch of 60 missing rows (a gap) and 3 missing rows (not a gap)."""
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0.0, 40.0, 1500))
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, t=t)
    x = data.x[:, :1] + 0.01 * data.x[:, 0].std() * rng.standard_normal((1500, 1))
    x[300:360] = np.nan
    x[900:903] = np.nan
    result = discover_hidden(x, ps.PolynomialLibrary(degree=3), t=t, feature_names=["x"],
                             verbose=False)
    return data, x, result


def test_random_times_and_gaps_give_the_exact_law(irregular_with_gaps):
    """xdot = h x with h = alpha - beta y, so dh/dt = gamma alpha - delta alpha x - gamma h
    + delta x h: each hidden-equation coefficient within 1% of the truth, confident."""
    _, _, result = irregular_with_gaps
    x, h = sp.symbols("x h0", real=True)
    alpha, gamma, delta = 1.0, 1.5, 0.075
    truth = {sp.Integer(1): gamma * alpha, x: -delta * alpha, h: -gamma, h * x: delta}
    assert result.hidden_names == ("h0",)
    assert set(result.equation("h0")) == set(truth)
    for feature, value in truth.items():
        assert result.coefficient("h0", feature) == pytest.approx(value, rel=0.01), feature
    assert result.confident, result.summary()


def test_segments_are_reported(irregular_with_gaps):
    data, x, result = irregular_with_gaps
    use = result.data_use
    assert (use.recordings, use.segments, use.missing_rows, use.samples) == (1, 2, 63, 1437)
    assert use.sources == ((0, 360, 1499), (0, 0, 299))  # the longest segment first
    assert "2 segments, 1437 samples used (63 rows with missing values dropped)" in \
        result.summary()
    rows = np.arange(360, 1500)
    rows = rows[np.isfinite(x[rows, 0])]
    np.testing.assert_array_equal(result.times, data.t[rows])
    assert result.compare_hidden(data.x_clean[rows, 1]).r2[0] > 0.999


def test_knots_follow_time_not_samples():
    """Knot spacing: one uniform series gets half its window (in samples); a second
    segment sampled twice as densely gets twice as many samples per knot (the same time);
    a short segment whose window its length limited sets nothing; when every window is
    limited, the narrowest one counts; at most 400 knots over the longest series."""
    t1 = np.arange(2000) * 0.01
    assert _knot_spacing([97], [False], [t1]) == [48]
    t2 = np.arange(500) * 0.005
    assert _knot_spacing([97, 195], [False, False], [t1, t2]) == [48, 97]
    assert _knot_spacing([97, 19], [False, True], [t1, t2[:100]]) == [48, 97]
    assert _knot_spacing([61, 19], [True, True], [t1[:305], t2[:100]]) == [4, 9]
    assert _knot_spacing([3], [False], [np.arange(40_000) * 0.01]) == [100]


def _coefficients(*series):
    """Stand-ins for stage one's coefficient series of one term on several segments."""
    from types import SimpleNamespace

    return [SimpleNamespace(term=lambda s, f, m=m: m, term_std=lambda s, f: np.full(50, 0.01),
                            active_terms=lambda: [("y", "x")]) for m in series]


def test_variation_is_pooled_over_segments():
    """A transient that sits at one level in one segment and at another in the next
    varies (a hidden state need not move in every segment); the same level in both is a
    constant."""
    flat = np.full(50, 2.0)
    assert _varying(_coefficients(flat, flat + 0.5), None) == [("y", "x")]
    assert _varying(_coefficients(flat, flat + 1e-3), None) == []
    ramp = np.linspace(2.0, 2.5, 50)
    assert _varying(_coefficients(flat, ramp), None) == [("y", "x")]
