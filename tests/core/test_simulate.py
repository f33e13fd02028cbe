"""Integration of a closed system: the rows a failed run reached are kept, checked
against analytic solutions; the rest are NaN."""

import numpy as np
import pytest
import torch
from torchdiffeq import odeint

from latentsindy._core.simulate import integrate


def quadratic(t, y):  # x' = x^2: x = 1 / (1 - t) from x(0) = 1, infinite at t = 1
    return y * y


def rotation(t, y):  # x' = -y, y' = x: (cos t, sin t) from (1, 0)
    return torch.stack([-y[1], y[0]])


def test_a_blow_up_keeps_the_rows_before_it():
    t = np.linspace(0.0, 2.0, 201)
    sim = integrate(quadratic, t, [1.0], ("x",), bound=1e3)
    assert sim.status == "blow_up" and not sim.success
    assert "blew up (state left the bounded region at t=0.99" in sim.message
    before = t <= 0.99  # where x = 100 < 1e3, one chunk of the output grid and more
    np.testing.assert_allclose(sim.x[before, 0], 1.0 / (1.0 - t[before]), rtol=1e-6)
    assert np.all(np.isnan(sim.x[t >= 1.0]))
    assert sim.n_evaluations > 0


@pytest.mark.parametrize("max_steps", [20, 50, 300])
def test_an_exhausted_budget_keeps_the_rows_reached(max_steps):
    """Every row up to where the failed run got (the latest time it evaluated the field
    at) is kept, however small the budget, within about twice the budget."""
    times = []

    def field(ti, y):
        times.append(float(ti))
        return rotation(ti, y)

    t = np.linspace(0.0, 2000.0, 20001)
    sim = integrate(field, t, [1.0, 0.0], ("x", "y"), bound=10.0, max_steps=max_steps)
    assert sim.status == "step_budget"
    assert f"budget of {max_steps} steps before reaching t=2000" in sim.message
    reached = max(times[:6 * max_steps])  # the failed run's evaluations come first
    kept = ~np.isnan(sim.x[:, 0])
    assert kept.sum() == np.sum(t <= reached) and kept[:kept.sum()].all()
    np.testing.assert_allclose(sim.x[kept], np.column_stack([np.cos(t[kept]), np.sin(t[kept])]),
                               atol=1e-6)
    assert 6 * max_steps < sim.n_evaluations == len(times) + 1 <= 2 * (6 * max_steps + 1) + 120


def test_a_run_that_succeeds_is_the_single_integration():
    """The success path is one odeint call: the same states to the bit, the same
    evaluations."""
    t = np.linspace(0.0, 10.0, 101)
    calls = [0]

    def counted(ti, y):
        calls[0] += 1
        return rotation(ti, y)

    sim = integrate(rotation, t, [1.0, 0.0], ("x", "y"), bound=10.0)
    assert sim.success and sim.message == "Integrated to the final time."
    with torch.no_grad():
        direct = odeint(counted, torch.tensor([1.0, 0.0], dtype=torch.float64),
                        torch.tensor(t), method="dopri5", rtol=1e-8, atol=1e-10)
    np.testing.assert_array_equal(sim.x, direct.numpy())
    assert sim.n_evaluations == calls[0]
    np.testing.assert_allclose(sim.x, np.column_stack([np.cos(t), np.sin(t)]), atol=1e-7)


@pytest.mark.parametrize("x0", [[2e3], [np.nan]])
def test_a_start_outside_the_bound_keeps_only_the_start(x0):
    sim = integrate(quadratic, np.linspace(0.0, 1.0, 5), x0, ("x",), bound=1e3)
    assert sim.status == "blow_up"
    np.testing.assert_array_equal(sim.x[0], x0)
    assert np.all(np.isnan(sim.x[1:]))
