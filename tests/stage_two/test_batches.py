"""A panel's recordings integrated side by side (``fit.batches``): the same numbers as
integrating them one by one, in a few calls."""

import numpy as np
import pytest
import sympy as sp
import torch

from latentsindy import systems
from latentsindy._stage_two.fit.batches import GROWTH, make_batches, run_groups
from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.fit.normal_equations import as_array
from latentsindy._stage_two.fit.refine import Problem
from latentsindy._stage_two.fit.shooting import BlowUp, Integrator, make_groups

X, Y, Z = sp.symbols("x y z", real=True)
FEATURES = (sp.Integer(1), X, Y, Z, X * Y, X * Z)
LORENZ = np.array([[0.0, -10.0, 10.0, 0.0, 0.0, 0.0],
                   [0.0, 28.0, -1.0, 0.0, 0.0, -1.0],
                   [0.0, 0.0, 0.0, -8.0 / 3.0, 1.0, 0.0]])
leaves = torch.utils._pytree.tree_leaves


def _panel(seed=0):
    """Seven recordings of Lorenz-like size, irregular times, spans from a fraction of a
    segment to several segments (grids of different lengths, so several batches and
    padded grids within a batch)."""
    rng = np.random.default_rng(seed)
    spans = [0.05, 0.08, 0.12, 0.3, 0.6, 0.45, 0.1]
    times = [np.sort(rng.uniform(0.0, s, 11 + 4 * k)) for k, s in enumerate(spans)]
    groups = make_groups(times, [np.zeros((len(t), 1)) for t in times], 0.25, 0.004)
    starts = rng.normal([1.0, 1.0, 20.0], 1.0, size=(sum(g.n_segments for g in groups), 3))
    system = ParametricSystem(("x", "y", "z"), 1, FEATURES, LORENZ, LORENZ != 0)
    return system, groups, starts


@pytest.mark.parametrize("in_numpy", [True, False])
def test_a_panel_side_by_side_equals_one_recording_at_a_time(in_numpy):
    """Every group's states, sensitivities and segment ends equal those of its own run
    (to 1e-14: the same arithmetic, the field's matrix products on more rows), with and
    without sensitivities and for the observed states alone, in numpy and in torch; the
    groups come back in their order; grids more than GROWTH apart go to separate
    batches, and a batch holds grids of different lengths (padded)."""
    system, groups, starts = _panel()
    batches = make_batches(groups)
    lengths = [sorted({len(groups[i].grid) for i, *_ in b.members}) for b in batches]
    assert len(batches) >= 2 and any(len(set(n)) > 1 for n in lengths)
    assert all(n[-1] <= GROWTH * n[0] for n in lengths)
    integrator = Integrator(system, 1e6)
    integrator.in_numpy = in_numpy
    for sens in (True, False):
        for components in (None, 1):
            apart = list(run_groups(integrator, LORENZ, starts, groups, None, sens,
                                    components))
            together = list(run_groups(integrator, LORENZ, starts, groups, batches, sens,
                                       components))
            assert [g for g, *_ in together] == groups
            for (_, segs, a), (_, segs_b, b) in zip(apart, together, strict=True):
                np.testing.assert_array_equal(segs, segs_b)
                for u, v in zip(leaves(a), leaves(b), strict=True):
                    assert u.shape == v.shape
                    torch.testing.assert_close(v, u, rtol=1e-14, atol=1e-14)


def test_make_batches_leaves_a_single_recording_alone():
    system, groups, _ = _panel()
    assert make_batches(groups[:1]) is None
    assert len(make_batches(groups[:2])) == 1  # grids within GROWTH: one batch


def test_a_recording_that_blows_up_is_reported_on_its_own():
    """``blow_ups``: the recording that leaves the bounded region comes back as None,
    the others as on their own; without it the batch raises BlowUp."""
    system, groups, starts = _panel()
    bad = groups[3]
    starts = starts.copy()
    starts[bad.first, 2] = 1e5  # z huge: x and y leave the bound at once
    integrator = Integrator(system, 1e6)
    batches = make_batches(groups)
    with pytest.raises(BlowUp):
        list(run_groups(integrator, LORENZ, starts, groups, batches, False))
    out = list(run_groups(integrator, LORENZ, starts, groups, batches, False, blow_ups=True))
    assert [run is None for _, _, run in out] == [g is bad for g in groups]
    for g, segs, run in out:
        if run is not None:
            own = integrator.run(LORENZ, starts[segs], g, sensitivities=False)
            for u, v in zip(leaves(own), leaves(run), strict=True):
                torch.testing.assert_close(v, u, rtol=1e-14, atol=1e-14)


def test_a_panel_problem_gives_the_same_normal_equations_and_scores_batched():
    """Prey-only Lotka-Volterra (x' = x h, the hidden h = a - b y) cut into five
    recordings: the normal equations, the continuity gap, the trajectories and the
    per-segment errors are those of the problem integrated recording by recording (to
    1e-12)."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=600, t_end=15.0,
                                  noise=0.01, seed=3)
    h = sp.Symbol("h", real=True)
    feats = (sp.Integer(1), X, X * h, h)
    coef = np.array([[0.0, 0.0, 1.0, 0.0], [1.5, -0.075, 0.075, -1.5]])
    free = np.array([[False] * 4, [True] * 4])
    system = ParametricSystem(("x", "h"), 1, feats, coef, free)
    cuts = [slice(0, 60), slice(100, 190), slice(250, 300), slice(320, 480), slice(500, 600)]
    guess = np.column_stack([data.x_clean[:, 0], 1.0 - 0.1 * data.x_clean[:, 1]])
    problem = Problem(system, [data.t[c] for c in cuts], [data.x[c, :1] for c in cuts],
                      [guess[c] for c in cuts])
    alone = Problem(system, [data.t[c] for c in cuts], [data.x[c, :1] for c in cuts],
                    [guess[c] for c in cuts])
    alone.batches = None
    assert problem.batches is not None
    starts = problem.initial_starts
    weights = np.ones(problem.n_segments)
    a, b = (p.equations(system, starts, weights, 1e2) for p in (alone, problem))
    np.testing.assert_allclose(b.grad, a.grad, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(as_array(b.matrix()), as_array(a.matrix()), rtol=1e-12,
                               atol=1e-12)
    assert b.cost == pytest.approx(a.cost, rel=1e-12)
    fit = problem.fit(max_iterations=5)
    assert problem._gap(fit.system, fit.starts) == pytest.approx(
        alone._gap(fit.system, fit.starts), rel=1e-12)
    for u, v in zip(problem.trajectories(fit), alone.trajectories(fit), strict=True):
        np.testing.assert_allclose(u, v, rtol=1e-12, atol=1e-12)
    which = np.arange(problem.n_segments) % 2 == 0
    np.testing.assert_allclose(problem.segment_errors(fit, which),
                               alone.segment_errors(fit, which), rtol=1e-12)
