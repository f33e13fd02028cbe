"""The loss on the knots equals the loss on the samples (float64 reference)."""

import numpy as np
import pytest
import torch

from latentsindy._stage_one.knot_loss import KnotLoss
from latentsindy._stage_one.training import roughness
from latentsindy.generators._knots import applies, knot_grid, structural_rows


def _samples(knots, n_times):
    """The piecewise-linear series at the samples (float64), as the decoder reads it."""
    left, frac = knot_grid(n_times, knots.shape[0])
    k = knots.reshape(knots.shape[0], -1).astype(np.float64)
    out = (1 - frac)[:, None] * k[left] + frac[:, None] * k[left + 1]
    return out.reshape(n_times, *knots.shape[1:])


@pytest.mark.parametrize("n_times, n_knots, n_traj", [(700, 64, 1), (2000, 256, 2),
                                                        (129, 64, 1), (127, 64, 1),
                                                        (1001, 32, 1)])
def test_terms_equal_the_samples(n_times, n_knots, n_traj):
    rng = np.random.default_rng(n_times)
    n, f = 2, 3
    theta = rng.standard_normal((n_traj, n_times, f)).astype(np.float32)
    xdot = rng.standard_normal((n_traj, n_times, n)).astype(np.float32)
    weights = rng.uniform(0.5, 1.5, (n_traj, n_times, n)).astype(np.float32)
    # smooth, with sign changes inside intervals and a few kinks
    grid = np.linspace(0, 6, n_knots)[:, None, None]
    xi = (np.sin(grid * rng.uniform(0.5, 3, (1, n, f))) + 0.1 * rng.standard_normal(
        (n_knots, n, f))).astype(np.float32)
    loss = KnotLoss(theta, xdot, weights, n_knots)
    on_samples = _samples(xi, n_times)  # (T, n, F)
    pred = np.einsum("btf,tnf->btn", theta.astype(np.float64), on_samples)
    mse = np.mean(weights * (pred - xdot) ** 2)
    got, _ = loss.misfit(xi)
    assert got == pytest.approx(mse, rel=1e-10)
    size, _ = loss.magnitude(xi)
    np.testing.assert_allclose(size, np.abs(on_samples).mean(axis=0), rtol=1e-5)
    value, _ = loss.roughness(xi, 0.5)
    first = np.abs(np.diff(on_samples, axis=0)).mean(axis=0)
    second = np.abs(np.diff(on_samples, 2, axis=0)).sum(axis=0) / (n_times - 2)
    np.testing.assert_allclose(value, 0.5 * second + 0.5 * first, rtol=1e-5)


def test_gradients_equal_autograd_on_the_samples():
    """Each term's gradient by the knots against autograd of the samples' formulas in
    float64 (the roughness through ``training.roughness``, its rows that can bend)."""
    rng = np.random.default_rng(1)
    n_times, n_knots = 500, 32
    theta = rng.standard_normal((1, n_times, 3)).astype(np.float32)
    xdot = rng.standard_normal((1, n_times, 2)).astype(np.float32)
    weights = rng.uniform(0.5, 1.5, xdot.shape).astype(np.float32)
    loss = KnotLoss(theta, xdot, weights, n_knots)
    xi = (0.5 + rng.standard_normal((n_knots, 2, 3))).astype(np.float32)
    left, frac = knot_grid(n_times, n_knots)
    knots = torch.tensor(xi, dtype=torch.float64, requires_grad=True)
    f = torch.tensor(frac)[:, None, None]
    track = (1 - f) * knots[left] + f * knots[left + 1]  # (T, n, F)
    rows = torch.as_tensor(structural_rows(n_times, n_knots))
    pred = torch.einsum("tf,tnf->tn", torch.tensor(theta[0], dtype=torch.float64), track)
    references = {
        "misfit": torch.mean(torch.tensor(weights[0], dtype=torch.float64)
                             * (pred - torch.tensor(xdot[0], dtype=torch.float64)) ** 2),
        "magnitude": track.abs().sum(dim=0).sum(),  # the knots' gradient is the sum's
        "roughness": roughness(track[None], None, rows).sum(),
    }
    ours = {"misfit": loss.misfit(xi)[1], "magnitude": loss.magnitude(xi)[1],
            "roughness": loss.roughness(xi, 0.5)[1]}
    for name, reference in references.items():
        (expected,) = torch.autograd.grad(reference, knots, retain_graph=True)
        np.testing.assert_allclose(ours[name], expected.numpy(), rtol=1e-4,
                                   atol=1e-6 * float(expected.abs().max()), err_msg=name)


def test_structural_rows_are_the_ones_that_can_be_non_zero():
    n_times, n_knots = 300, 32
    rows = structural_rows(n_times, n_knots)
    rng = np.random.default_rng(2)
    curve = np.diff(_samples(rng.standard_normal((n_knots, 1)), n_times), 2, axis=0)[:, 0]
    assert np.all(np.abs(curve[~rows]) < 1e-12)  # zero but for float64 rounding
    assert np.all(np.abs(curve[rows]) > 1e-9)  # random knots: every other row bends
    # one or two rows per interior knot
    assert n_knots - 2 <= rows.sum() <= 2 * (n_knots - 2)
    assert not applies(100, 64, True) and not applies(1000, 64, False)


def test_the_rows_that_cannot_bend_give_no_gradient():
    """On a straight line the samples' float32 second differences are rounding noise
    with random signs; with the rows that can bend only, a sample that no such row
    reads gets no gradient (total variation pushes every slope alike, so it adds none
    inside)."""
    n_times, n_knots = 2000, 256
    knots = torch.linspace(0.3, 1.7, n_knots, dtype=torch.float32)
    track = torch.nn.functional.interpolate(knots[None, None], size=n_times, mode="linear",
                                            align_corners=True)[0, 0]
    rows = torch.as_tensor(structural_rows(n_times, n_knots))
    noise = (track[2:] - 2 * track[1:-1] + track[:-2]) != 0
    assert int((noise & ~rows).sum()) > 500  # what the samples' differences give
    read = torch.zeros(n_times, dtype=torch.bool)  # samples read by a row that can bend
    for shift in range(3):
        read[shift:n_times - 2 + shift] |= rows
    for given, free in ((rows, ~read), (None, None)):
        leaf = track.reshape(1, n_times, 1).clone().requires_grad_(True)
        roughness(leaf, None, given).sum().backward()
        moved = leaf.grad[0, 1:-1, 0] != 0
        if given is None:  # without the rows, the noise moves most samples
            assert int(moved.sum()) > n_times // 2
        else:
            assert not bool((moved & free[1:-1]).any())
