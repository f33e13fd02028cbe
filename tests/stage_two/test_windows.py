"""A long recording judged on windows of it (``fit.windows``): the windows are whole
segments of the recording, spread over it, and their residuals, sensitivities and noise
model are the recording's own on those segments."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import sympy as sp
import torch

from latentsindy import discover_hidden, systems
from latentsindy._stage_two.fit import windows
from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.fit.refine import Problem
from latentsindy._stage_two.fit.windows import JUDGED, LONG, WINDOWS, judged_part

X, H = sp.symbols("x h", real=True)


def _both(n_times, t_end):
    """Lotka-Volterra with both states observed (no hidden state) as a refinement
    problem."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=n_times, t_end=t_end,
                                  noise=0.01, seed=5)
    y = sp.Symbol("y", real=True)
    feats = (X, y, X * y)
    coef = np.array([[1.0, 0.0, -0.1], [0.0, -1.5, 0.075]])
    system = ParametricSystem(("x", "y"), 2, feats, coef, coef != 0)
    return system, Problem(system, [data.t], [data.x], [data.x_clean])


def _problem(n_times, t_end, rng_seed=3, ar1=False, gap=False):
    """Prey-only Lotka-Volterra (x' = x h, h = a - b y) as a refinement problem."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=n_times, t_end=t_end,
                                  noise=0.01, seed=rng_seed)
    x = data.x[:, :1].copy()
    if ar1:  # strongly correlated noise on top: the AR(1) model and its carry-over
        e = np.zeros(len(x))
        rng = np.random.default_rng(rng_seed)
        for i in range(1, len(e)):
            e[i] = 0.9 * e[i - 1] + 0.2 * rng.standard_normal()
        x[:, 0] += e
    feats = (sp.Integer(1), X, X * H, H)
    coef = np.array([[0.0, 0.0, 1.0, 0.0], [1.5, -0.075, 0.075, -1.5]])
    free = np.array([[False] * 4, [True] * 4])
    system = ParametricSystem(("x", "h"), 1, feats, coef, free)
    guess = np.column_stack([data.x_clean[:, 0], 1.0 - 0.1 * data.x_clean[:, 1]])
    cuts = [slice(0, n_times // 3), slice(n_times // 3 + 50, n_times)] if gap else [
        slice(0, n_times)]
    return system, Problem(system, [data.t[c] for c in cuts], [x[c] for c in cuts],
                           [guess[c] for c in cuts])


def test_a_recording_of_at_most_long_samples_is_judged_whole():
    _, problem = _problem(LONG, 400.0)
    assert judged_part(problem) is None


@pytest.mark.parametrize("kind", ["white", "ar1", "both observed"])
def test_windows_are_whole_segments_spread_over_the_recording(kind):
    """``WINDOWS`` runs of whole segments, the first at the start and the last at the
    end, about ``JUDGED`` samples in all; every window's data, sample times and AR(1)
    carry-over are the recording's own on its segments; and its residuals at the
    recording's starts are the recording's residuals on those segments."""
    ar1 = kind == "ar1"
    system, problem = _both(20000, 500.0) if kind == "both observed" else _problem(
        20000, 500.0, ar1=ar1)
    assert (problem.carry is not None) == ar1
    part = judged_part(problem)
    assert len(part.groups) == WINDOWS
    assert part.rows[0] == 0 and part.rows[-1] == problem.n_segments - 1
    n_obs = problem.n_obs
    per_segment = problem.n_data / n_obs / problem.n_segments
    assert part.n_data % n_obs == 0
    assert abs(part.n_data / n_obs - JUDGED) <= WINDOWS * per_segment
    widths = {g.n_segments for g in part.groups}
    assert len(widths) == 1 and WINDOWS * widths.pop() * 2 <= problem.n_segments
    full = problem.groups[0]
    for i, g in enumerate(part.groups):
        rows = part.rows[g.first:g.first + g.n_segments]
        assert np.all(np.diff(rows) == 1)  # one run of consecutive segments
        torch.testing.assert_close(g.observed, full.observed[rows], rtol=0, atol=0)
        np.testing.assert_array_equal(g.starts, full.starts[rows])
        mask = g.mask.numpy()
        np.testing.assert_array_equal(part.observed[i][g.sample_index[mask]],
                                      problem.observed[0][full.sample_index[rows][mask]])
        np.testing.assert_array_equal(part.times[i][g.sample_index[mask]],
                                      problem.times[0][full.sample_index[rows][mask]])
        if ar1:
            torch.testing.assert_close(part.carry[i], problem.carry[0][rows], rtol=0, atol=0)
    starts = problem.initial_starts
    np.testing.assert_array_equal(part.initial_starts, starts[part.rows])
    ones = np.ones(problem.n_segments)
    whole = problem.equations(system, starts, ones, 1.0, jacobian=False)
    only = np.zeros(problem.n_segments)
    only[part.rows] = 1.0  # the recording's data weighted to the windows' segments
    windows = part.equations(system, starts[part.rows], np.ones(part.n_segments), 1.0,
                             jacobian=False)
    assert windows.data_cost > 0
    chosen = problem.equations(system, starts, only, 1.0, jacobian=False)
    assert windows.data_cost == pytest.approx(chosen.data_cost, rel=1e-12)
    assert windows.data_cost < 0.5 * whole.data_cost
    errors = part.segment_errors(_at(part, system, starts[part.rows]), np.ones(part.n_segments,
                                                                               bool))
    which = np.zeros(problem.n_segments, bool)
    which[part.rows] = True
    np.testing.assert_allclose(errors, problem.segment_errors(_at(problem, system, starts),
                                                              which), rtol=1e-12)


def test_windows_are_counted_in_samples_where_a_recording_is_sparse():
    """A dense recording and a sparse one (7 samples over six times its span, most of
    its segments empty): every window holds about ``JUDGED / WINDOWS`` samples, none is
    an empty run of segments, and the part holds only segments with samples in its
    runs."""
    system, _ = _problem(1000, 10.0)
    dense = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=17000, t_end=170.0,
                                   noise=0.01, seed=3)
    sparse = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=7, t_end=1000.0,
                                    noise=0.01, seed=4)

    def guess(d):
        return np.column_stack([d.x_clean[:, 0], 1.0 - 0.1 * d.x_clean[:, 1]])

    problem = Problem(system, [dense.t, sparse.t], [dense.x[:, :1], sparse.x[:, :1]],
                      [guess(dense), guess(sparse)])
    part = judged_part(problem)
    samples = [int(g.mask.sum()) for g in part.groups]
    assert all(n > 0 for n in samples)
    assert len(samples) == WINDOWS and min(samples) >= JUDGED / WINDOWS
    assert sum(samples) <= JUDGED + WINDOWS * 50
    np.testing.assert_array_equal(part.initial_starts, problem.initial_starts[part.rows])


def test_windows_stay_within_their_recordings():
    """Where the data have two recordings (a gap), a window that would cross from one to
    the other is two windows, each inside its recording."""
    _, problem = _problem(24000, 600.0, gap=True)
    part = judged_part(problem)
    owners = []
    for g in part.groups:
        rows = part.rows[g.first:g.first + g.n_segments]
        owner = {next(k for k, h in enumerate(problem.groups)
                      if h.first <= r < h.first + h.n_segments) for r in rows}
        assert len(owner) == 1
        owners += owner
    assert set(owners) == {0, 1}
    assert len(part.groups) == WINDOWS + 1  # one window cut in two


def _at(problem, system, starts):
    """A stand-in fit at (system, starts), for the error functions."""
    from latentsindy._stage_two.fit.refine import Fit

    return Fit(system, starts, 0.0, 0.0, problem.n_data, 0.0, 0, np.zeros((0, 0)))


def test_a_long_recording_judged_on_windows_finds_the_law_on_every_sample(monkeypatch):
    """Prey-only Lotka-Volterra at 1% noise, 10,000 samples judged on windows (of about
    2,000 samples here, to keep the test short): the law is found with its hidden
    predator, confident, fitted on every sample (the hidden series covers the whole
    recording and is the predator up to an affine map)."""
    import pysindy as ps

    monkeypatch.setattr(windows, "JUDGED", 2000)
    monkeypatch.setattr(windows, "LONG", 8000)
    judged = []
    real = windows._part
    monkeypatch.setattr(windows, "_part", lambda *a: judged.append(1) or real(*a))

    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=10000, t_end=125.0,
                                  noise=0.01, seed=0)
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3, include_bias=False),
                             t=data.t, feature_names=["x"], hidden_names=["h"],
                             verbose=False)
    assert result.confident, result.summary()
    assert len(result.hidden_names) == 1 and "10000 samples used" in result.summary()
    assert result.states.shape == (10000, 2)
    cmp = result.compare_hidden(data.x_clean[:, 1])
    assert cmp.r2[0] >= 0.999
    assert cmp.scale[0, 0] == pytest.approx(-10.0, rel=1e-2)  # y = (alpha - h) / beta
    counts = {}
    for term in result.terms:
        if term.value != 0:
            counts[term.state] = counts.get(term.state, 0) + 1
    assert counts == {"x": 1, "h": 4}, result.summary()  # x' = h x; h' = a + b x + c h + d h x
    assert judged  # it was judged on windows, and the summary says so
    assert ("the terms were chosen, and the held-out scores (this system's and the "
            "alternatives') taken, on 4 windows of about") in " ".join(result.summary().split())


def test_only_the_chosen_system_is_fitted_on_every_sample(monkeypatch):
    """A hypothesis first fitted on the windows (``Trial.whole``: its recording's whole
    problem) is judged there: its verdict is the windows' and keeps the whole problem
    (its size counts one recording). Ranking fits the chosen one on every segment
    (``on_whole``: its own starts on the windows, the guesses elsewhere; its held-out
    score stays); where that fails it is unscored and the next is chosen."""
    from latentsindy._stage_two import judge
    from latentsindy._stage_two.verdict import Trial, finish, finished, on_whole, unscored

    system, problem = _problem(20000, 500.0)
    part = judged_part(problem)
    first = part.fit(system, max_iterations=10)
    proposal = SimpleNamespace(structure=SimpleNamespace(pivots=((0, 2),)), order=1,
                               nested=(), stage_one=False)
    trial = Trial(proposal, part, first, np.zeros_like(system.free), 1.0, problem)
    still = (first, (), 1.0, 0.1, np.ones(3))
    judged = finished(trial, still)
    assert judged.problem is part and judged.whole is problem and judged.cv == 1.0
    assert judged.size == system.n_parameters(1)  # the windows are one recording
    chosen = on_whole(judged)
    assert chosen.problem is problem and chosen.whole is None and chosen.cv == 1.0
    assert len(chosen.fit.starts) == problem.n_segments and chosen.fit.n_data == problem.n_data
    # the guesses are the truth here: the fit ends at the noise
    assert chosen.fit.residual_variance == pytest.approx(1.0, abs=0.1)
    rejected = on_whole(unscored(trial, "rejected"))
    assert rejected.problem is problem and rejected.cv == rejected.fit.residual_variance

    ordered, _, verdicts = judge._ranked([judged])
    assert ordered[0].problem is problem and verdicts == [ordered[0]]
    free = system.free.copy()
    free[0, 1] = True  # another system, scoring worse, judged on every sample
    other = ParametricSystem(system.state_names, 1, system.features, system.coef, free)
    worse = replace(judged, fit=replace(chosen.fit, system=other), problem=problem,
                    whole=None, cv=2.0)
    monkeypatch.setattr(judge, "on_whole", lambda v: "does not join")
    ordered, _, verdicts = judge._ranked([judged, worse])
    assert ordered[0] is worse and ordered[1].history == ("does not join",)
    assert judge._ranked([unscored(trial, "rejected")])[0] == []
    judged = finish(trial)  # selected and scored on the windows, as it was fitted
    assert judged.scored and judged.problem is part and judged.whole is problem


def test_the_simulated_reference_of_a_windowed_score_is_taken_on_the_windows(monkeypatch):
    """A score taken on windows is read against a reference simulated and scored on the
    same windows (the system refitted there), a whole recording's against one on it."""
    from latentsindy._stage_two import assemble

    seen = []
    monkeypatch.setattr(assemble, "expected_score",
                        lambda problem, fit: seen.append((problem, fit)) or 1.0)
    system, problem = _problem(20000, 500.0)
    fit = problem.fit(system, max_iterations=5)
    assert assemble._reference(problem, fit) == 1.0
    (used, own), = seen
    part = judged_part(problem)
    np.testing.assert_array_equal(used.rows, part.rows)
    assert len(own.starts) == part.n_segments and own.n_data == part.n_data
    short_system, short = _problem(2000, 50.0)
    short_fit = short.fit(short_system, max_iterations=5)
    assemble._reference(short, short_fit)
    assert seen[-1] == (short, short_fit)
