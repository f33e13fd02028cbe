"""The loss on the knots equals the loss on the samples (float64 reference)."""

import numpy as np
import pytest
import torch

from latentsindy._stage_one.knot_loss import KnotLoss
from latentsindy._stage_one.loss import roughness
from latentsindy.generators._knots import applies, curve_rows, knot_grid


def _samples(knots, n_times):
    """The piecewise-linear series at the samples (float64), as the decoder reads it."""
    left, frac = knot_grid(n_times, knots.shape[0])
    k = knots.reshape(knots.shape[0], -1).astype(np.float64)
    out = (1 - frac)[:, None] * k[left] + frac[:, None] * k[left + 1]
    return out.reshape(n_times, *knots.shape[1:])


GRIDS = [(700, 64, 1, 3), (2000, 256, 2, 3), (129, 64, 1, 3),
         (127, 64, 1, 3),  # exactly two samples per interval: every other one on a knot
         (1001, 32, 1, 3),
         (100, 32, 2, 8)]  # a wide library: the misfit read at the samples


@pytest.mark.parametrize("n_times, n_knots, n_traj, f", GRIDS)
def test_terms_equal_the_samples(n_times, n_knots, n_traj, f):
    rng = np.random.default_rng(n_times)
    n = 2
    theta = rng.standard_normal((n_traj, n_times, f)).astype(np.float32)
    xdot = rng.standard_normal((n_traj, n_times, n)).astype(np.float32)
    weights = rng.uniform(0.5, 1.5, (n_traj, n_times, n)).astype(np.float32)
    # smooth, with sign changes inside intervals and a few kinks
    grid = np.linspace(0, 6, n_knots)[:, None, None]
    xi = (np.sin(grid * rng.uniform(0.5, 3, (1, n, f))) + 0.1 * rng.standard_normal(
        (n_knots, n, f))).astype(np.float32)
    loss = KnotLoss(theta, xdot, weights, n_knots)
    assert loss.on_samples == (n_knots * f > 2 * n_times)
    on_samples = _samples(xi, n_times)  # (T, n, F)
    pred = np.einsum("btf,tnf->btn", theta.astype(np.float64), on_samples)
    mse = np.mean(weights * (pred - xdot) ** 2)
    got, _ = loss.misfit(xi)
    assert got == pytest.approx(mse, rel=1e-10 if not loss.on_samples else 1e-5)
    size, _ = loss.magnitude(xi)
    np.testing.assert_allclose(size, np.abs(on_samples).mean(axis=0), rtol=1e-5)
    value, _ = loss.roughness(xi)
    first = np.abs(np.diff(on_samples, axis=0)).mean(axis=0)
    second = np.abs(np.diff(on_samples, 2, axis=0)).sum(axis=0) / (n_times - 2)
    np.testing.assert_allclose(value, 0.5 * second + 0.5 * first, rtol=1e-5)


@pytest.mark.parametrize("n_times, n_knots, n_traj, n_features", GRIDS)
def test_gradients_equal_autograd_on_the_samples(n_times, n_knots, n_traj, n_features):
    """Each term's gradient by the knots against autograd of the samples' formulas in
    float64; the roughness with every second difference (those that cannot bend add
    nothing in exact arithmetic)."""
    rng = np.random.default_rng(1)
    theta = rng.standard_normal((n_traj, n_times, n_features)).astype(np.float32)
    xdot = rng.standard_normal((n_traj, n_times, 2)).astype(np.float32)
    weights = rng.uniform(0.5, 1.5, xdot.shape).astype(np.float32)
    loss = KnotLoss(theta, xdot, weights, n_knots)
    xi = (0.5 + rng.standard_normal((n_knots, 2, n_features))).astype(np.float32)
    left, frac = knot_grid(n_times, n_knots)
    knots = torch.tensor(xi, dtype=torch.float64, requires_grad=True)
    f = torch.tensor(frac)[:, None, None]
    track = (1 - f) * knots[left] + f * knots[left + 1]  # (T, n, F)
    pred = torch.einsum("btf,tnf->btn", torch.tensor(theta, dtype=torch.float64), track)
    references = {
        "misfit": torch.mean(torch.tensor(weights, dtype=torch.float64)
                             * (pred - torch.tensor(xdot, dtype=torch.float64)) ** 2),
        "magnitude": track.abs().sum(dim=0).sum(),  # the knots' gradient is the sum's
        "roughness": roughness(track[None]).sum(),
    }
    ours = {"misfit": loss.misfit(xi)[1], "magnitude": loss.magnitude(xi)[1],
            "roughness": loss.roughness(xi)[1]}
    for name, reference in references.items():
        (expected,) = torch.autograd.grad(reference, knots, retain_graph=True)
        np.testing.assert_allclose(ours[name], expected.numpy(), rtol=1e-4,
                                   atol=1e-6 * float(expected.abs().max()), err_msg=name)


def _rows_that_bend(n_times, n_knots):
    rows, _, _, _ = curve_rows(*knot_grid(n_times, n_knots), n_knots)
    out = np.zeros(n_times - 2, dtype=bool)
    out[rows] = True
    return out


def test_the_rows_that_bend_are_the_ones_that_can_be_non_zero():
    n_times, n_knots = 300, 32
    rows = _rows_that_bend(n_times, n_knots)
    rng = np.random.default_rng(2)
    curve = np.diff(_samples(rng.standard_normal((n_knots, 1)), n_times), 2, axis=0)[:, 0]
    assert np.all(np.abs(curve[~rows]) < 1e-12)  # zero but for float64 rounding
    assert np.all(np.abs(curve[rows]) > 1e-9)  # random knots: every other row bends
    assert n_knots - 2 <= rows.sum() <= 2 * (n_knots - 2)  # one or two per interior knot
    assert not applies(100, 64, True) and not applies(1000, 64, False)


def test_rows_that_cannot_bend_do_not_move_the_knots():
    """The samples' second differences inside an interval are zero in exact arithmetic
    and rounding noise in float32, with random signs; their gradient pattern (1, -2, 1)
    is itself a second difference, which the linear interpolation's weights annul: the
    knots' gradient from them is rounding, whatever their signs (so leaving them out,
    as the knots' loss does, changes the rounding only)."""
    n_times, n_knots = 2000, 256
    left, frac = knot_grid(n_times, n_knots)
    bends = _rows_that_bend(n_times, n_knots)
    signs = np.random.default_rng(0).choice([-1.0, 1.0], n_times - 2)

    def knots_gradient(rows):
        g2 = signs * rows
        g = np.zeros(n_times)
        g[2:] += g2
        g[1:-1] -= 2 * g2
        g[:-2] += g2
        out = np.bincount(left, weights=(1 - frac) * g, minlength=n_knots)
        return out + np.bincount(left + 1, weights=frac * g, minlength=n_knots)

    assert np.abs(knots_gradient(~bends)).max() < 1e-9
    assert np.abs(knots_gradient(bends)).max() > 0.1
