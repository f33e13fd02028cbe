"""The discrete steps between the phases: pruned terms the data need come back (a
forward step); variation the data do not need is frozen (a backward step)."""

import numpy as np
import pytest
import torch
from torch import nn

from latentsindy._stage_one.coefficient_model import CoefficientModel
from latentsindy._stage_one.decisions import (
    freeze_constant_terms,
    restore_absorbed_terms,
    restore_terms,
)
from latentsindy._stage_one.flat_adam import FlatAdam
from latentsindy._stage_one.loss import TV_SHARE, roughness


class _Flat(nn.Module):
    """A generator with no time variation (Xi = constants)."""

    def __init__(self, n_out):
        super().__init__()
        self.n_out = n_out

    def sample(self, inputs, n_samples):
        return torch.zeros(max(n_samples, 1), inputs.shape[-1], self.n_out), torch.zeros(())


def _problem(small=-0.5):
    """Normalised library [a, b, c] with b nearly collinear with a; xdot = 2a + small*b."""
    t = np.linspace(0, 20, 2000)
    a = np.sin(t)
    b = np.sin(t) + 0.3 * np.cos(1.3 * t)
    c = np.cos(3.7 * t)
    theta = np.stack([a, b, c], axis=1)
    theta /= np.sqrt(np.mean(theta**2, axis=0))
    truth = np.array([2.0, small, 0.0])
    xdot = theta @ truth
    scale = np.sqrt(np.mean(xdot**2))
    as_t = lambda v: torch.as_tensor(v, dtype=torch.float32)  # noqa: E731
    return (as_t(theta[None]), as_t(xdot[None, :, None] / scale), truth / scale,
            torch.zeros(1, 2, 2000))


def _model(theta, xdot, support):
    support = torch.as_tensor(support)[None]
    a = theta[0][:, support[0]]
    constants = torch.zeros(1, 3)
    constants[0, support[0]] = torch.linalg.lstsq(a, xdot[0]).solution[:, 0]
    return CoefficientModel(_Flat(3), constants, support, torch.ones(1, 3))


def test_collinear_term_is_restored_with_exact_constants():
    """b explains little beyond a, but it is real and above threshold: it returns, and
    the joint refit gives the true constants (1e-4); c, which explains nothing, stays out;
    the restored term is a constant."""
    theta, xdot, truth, inputs = _problem()
    model = _model(theta, xdot, [True, False, False])
    weights = torch.ones_like(xdot)
    restored = restore_terms(model, theta, xdot, weights, inputs, 0.05, torch.tensor([True]))
    assert restored == [(0, 1)]
    assert model.support.tolist() == [[True, True, False]]
    assert model.time_varying.tolist() == [[1.0, 0.0, 1.0]]
    np.testing.assert_allclose(model.constants[0, :2].detach().numpy(), truth[:2], atol=1e-4)


def test_small_term_and_fixed_rows_are_not_restored():
    """A real term below the threshold stays pruned; rows with a user-fixed support are
    left alone."""
    theta, xdot, truth, inputs = _problem(small=-0.02)
    assert abs(truth[1]) < 0.05
    model = _model(theta, xdot, [True, False, False])
    weights = torch.ones_like(xdot)
    assert restore_terms(model, theta, xdot, weights, inputs, 0.05, torch.tensor([True])) == []
    theta, xdot, _, inputs = _problem()
    model = _model(theta, xdot, [True, False, False])
    assert restore_terms(model, theta, xdot, weights, inputs, 0.05, torch.tensor([False])) == []
    assert model.support.tolist() == [[True, False, False]]


class _Given(nn.Module):
    """A generator that returns a fixed coefficient series (1, T, n_out)."""

    def __init__(self, series):
        super().__init__()
        self.series = series

    def sample(self, inputs, n_samples):
        return self.series.expand(max(n_samples, 1), -1, -1), torch.zeros(())


def _varying_problem():
    """xdot = (2 + 0.5 sin 0.3t) a - 0.5 b; the model's b also varies (0.1 cos 2.1t),
    a variation the data do not contain."""
    t = np.linspace(0, 20, 2000)
    theta, _, _, inputs = _problem()
    varying = np.stack([0.5 * np.sin(0.3 * t), 0.1 * np.cos(2.1 * t), 0 * t], axis=1)
    xdot = theta[0].numpy() @ np.array([2.0, -0.5, 0.0]) + theta[0, :, 0].numpy() * varying[:, 0]
    model = CoefficientModel(_Given(torch.as_tensor(varying[None], dtype=torch.float32)),
                             torch.tensor([[2.0, -0.5, 0.0]]), torch.tensor([[True, True, False]]),
                             torch.ones(1, 3))
    return model, theta, torch.as_tensor(xdot[None, :, None], dtype=torch.float32), inputs, varying


def test_unneeded_variation_is_frozen_at_its_mean():
    """b's variation explains nothing beyond constants: b becomes the constant mean of its
    coefficient (1e-6); a's real variation stays; the inactive c is not touched."""
    model, theta, xdot, inputs, varying = _varying_problem()
    weights = torch.ones_like(xdot)
    frozen = freeze_constant_terms(model, theta, xdot, weights, inputs, 1e-3,
                                   torch.tensor([True]))
    assert frozen == [(0, 1)]
    assert model.time_varying.tolist() == [[1.0, 0.0, 1.0]]
    assert abs(float(model.constants[0, 1].detach()) - (-0.5 + varying[:, 1].mean())) < 1e-6


def test_variation_is_kept_when_it_pays_and_on_fixed_rows():
    """A cost above what a's variation explains beyond constants (its least-squares
    share of the mean squared derivative) freezes it too; rows with a user-fixed support
    are left alone whatever the cost."""
    model, theta, xdot, inputs, _ = _varying_problem()
    weights = torch.ones_like(xdot)
    columns = torch.cat([theta[0], theta[0, :, :1] * model.generator.series[0, :, :1]], dim=1)
    fit = torch.linalg.lstsq(theta[0].double(), xdot[0].double()).solution
    misfit = float(torch.mean((theta[0].double() @ fit - xdot[0]) ** 2))
    assert misfit > 1e-3  # the variation matters: constants alone leave this misfit
    assert torch.linalg.matrix_rank(columns) == 4
    assert freeze_constant_terms(model, theta, xdot, weights, inputs, 0.5 * misfit,
                                 torch.tensor([True])) == [(0, 1)]
    model, theta, xdot, inputs, _ = _varying_problem()
    assert freeze_constant_terms(model, theta, xdot, weights, inputs, 2.0 * misfit,
                                 torch.tensor([True])) == [(0, 1), (0, 0)]
    model, theta, xdot, inputs, _ = _varying_problem()
    assert freeze_constant_terms(model, theta, xdot, weights, inputs, 1e6,
                                 torch.tensor([False])) == []
    assert model.time_varying.tolist() == [[1.0, 1.0, 1.0]]


def _absorbing_problem(beta):
    """Columns a > 0 and b; the model has only a, with the varying coefficient
    c(t) = 2 + beta b / a + 0.1 sin(0.2 t): b's role absorbed into a's variation."""
    t = np.linspace(0, 20, 2000)
    a, b = 1.0 + 0.5 * np.sin(t), np.cos(1.3 * t)
    theta = torch.as_tensor(np.stack([a, b], axis=1)[None], dtype=torch.float32)
    varying = np.stack([beta * b / a + 0.1 * np.sin(0.2 * t), 0 * t], axis=1)
    xdot = (2.0 + varying[:, 0]) * a
    model = CoefficientModel(_Given(torch.as_tensor(varying[None], dtype=torch.float32)),
                             torch.tensor([[2.0, 0.0]]), torch.tensor([[True, False]]),
                             torch.tensor([[1.0, 0.0]]))
    return (model, theta, torch.as_tensor(xdot[None, :, None], dtype=torch.float32),
            torch.zeros(1, 2, 2000))


def test_term_absorbed_into_a_varying_coefficient_is_restored():
    """b's role hidden in a's varying coefficient comes back as a constant with the
    least-squares coefficient of the contribution on [a, b] (1e-4; within 5% of the
    true -0.5: the drift of c is not orthogonal to b); a keeps varying."""
    model, theta, xdot, inputs = _absorbing_problem(-0.5)
    weights = torch.ones_like(xdot)
    restored = restore_absorbed_terms(model, theta, xdot, weights, inputs, 0.05,
                                      torch.tensor([True]))
    assert restored == [(0, 1)]
    assert model.support.tolist() == [[True, True]]
    assert model.time_varying.tolist() == [[1.0, 0.0]]
    contribution = theta[0, :, 0] * (2.0 + model.generator.series[0, :, 0])
    expected = np.linalg.lstsq(theta[0].double().numpy(), contribution.double().numpy(),
                               rcond=None)[0][1]
    found = float(model.constants[0, 1].detach())
    assert abs(found / expected - 1) < 1e-4
    assert abs(found / -0.5 - 1) < 0.05


def test_variation_unrelated_to_pruned_terms_is_left_alone():
    """A varying coefficient that is not a pruned column in disguise (a hidden state)
    restores nothing; neither does a fixed row."""
    model, theta, xdot, inputs = _absorbing_problem(0.0)
    weights = torch.ones_like(xdot)
    assert restore_absorbed_terms(model, theta, xdot, weights, inputs, 0.05,
                                  torch.tensor([True])) == []
    model, theta, xdot, inputs = _absorbing_problem(-0.5)
    assert restore_absorbed_terms(model, theta, xdot, weights, inputs, 0.05,
                                  torch.tensor([False])) == []
    assert model.support.tolist() == [[True, False]]


def test_roughness_per_unit_time():
    """The roughness prior on irregular times: equal spacings give the plain second
    differences; a parabola sampled at uneven times has the same curvature everywhere
    (divided differences); two samples at one float32 position (a zero step) give a
    finite prior, not 0/0."""
    t = np.linspace(0.0, 1.0, 11)
    track = torch.tensor((t**2)[None, :, None], dtype=torch.float32)
    equal = roughness(track, torch.full((10,), 0.1))
    assert torch.allclose(equal, roughness(track), rtol=1e-5)
    uneven = np.sort(np.r_[0.0, 1.0, np.random.default_rng(0).uniform(0, 1, 9)])
    steps = torch.tensor(np.diff(uneven), dtype=torch.float32)
    parabola = torch.tensor((uneven**2)[None, :, None], dtype=torch.float32)
    curvature = 2.0 * (steps.mean() ** 2)  # second derivative in units of the mean step
    expected = 0.5 * curvature * torch.mean((steps[1:] + steps[:-1]) / 2 / steps.mean())
    tv = roughness(parabola, steps) - expected
    assert torch.allclose(tv, TV_SHARE * torch.diff(parabola, dim=1).abs().mean(), rtol=1e-4)
    steps[4] = 0.0
    assert torch.isfinite(roughness(parabola, steps)).all()


def _adam_pair(shapes, seed=0):
    torch.manual_seed(seed)
    ref = [nn.Parameter(torch.randn(s)) for s in shapes]
    flat = [nn.Parameter(p.detach().clone()) for p in ref]
    return ref, flat


@pytest.mark.parametrize("compiled", [False, True])
def test_flat_adam_is_torch_adam_with_clipping(compiled):
    """The flat optimiser replays torch.optim.Adam(foreach) + clip_grad_norm_, clipped
    steps and unclipped steps alike, with a learning rate changed every step: to the
    bit with torch's kernels; compiled (the CPU's default), the same arithmetic in
    float32 rounded in its own order, within a few float32 roundings after 200 steps."""
    shapes = [(32, 2, 5), (32,), (32, 32, 5), (8, 64), (1024, 4), (3, 32, 1), (1, 3)]
    ref, flat = _adam_pair(shapes)
    torch_adam = torch.optim.Adam(ref, lr=3e-3, foreach=True)
    ours = FlatAdam(flat, lr=3e-3, compiled=compiled)
    assert ours.compiled is compiled
    assert FlatAdam([nn.Parameter(torch.ones(2))], lr=0.1).compiled  # the CPU's default
    clipped = 0
    for step in range(200):
        grads = [torch.randn(s) * (0.002 if step % 2 else 0.5) for s in shapes]
        lr = 3e-3 * (1 - step / 400)
        torch_adam.param_groups[0]["lr"] = ours.lr = lr
        torch_adam.zero_grad(set_to_none=True)
        for p, g in zip(ref, grads, strict=True):
            p.grad = g.clone()
        norm = nn.utils.clip_grad_norm_(ref, 1.0)
        clipped += bool(norm > 1.0)
        torch_adam.step()
        ours.zero_grad()
        for p, g in zip(flat, grads, strict=True):
            p.grad.copy_(g)
        ours.step(max_norm=1.0)
        if compiled:  # each step's clipped gradient, as torch's
            for p, g in zip(ref, ours.grads, strict=True):
                torch.testing.assert_close(g, p.grad, rtol=1e-5, atol=1e-9)
    assert 50 < clipped < 150  # both branches of the clipping ran
    if compiled:  # parameters of size ~1 moved by ~0.3 in 200 steps of 3e-3
        for a, b in zip(ref, flat, strict=True):
            torch.testing.assert_close(b.detach(), a.detach(), rtol=0, atol=2e-6)
    else:
        assert all(torch.equal(a, b) for a, b in zip(ref, flat, strict=True))
    ours.release()
    assert all(p.grad is None for p in flat)
    storages = {p.untyped_storage().data_ptr() for p in flat}
    assert len(storages) == len(flat)  # each parameter owns its storage again


def test_flat_adam_compiled_needs_float32_on_the_cpu():
    p = nn.Parameter(torch.ones(3, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"needs float32 .* got torch.float64 on cpu"):
        FlatAdam([p], lr=0.1, compiled=True)
    assert p.grad is None  # refused before the parameter was rebound to a flat buffer
    assert not FlatAdam([p], lr=0.1).compiled  # the default there: torch's kernels


def test_flat_adam_gradients_accumulate_in_its_buffer():
    layer = nn.Linear(3, 2)
    params = list(layer.parameters())
    opt = FlatAdam(params, lr=0.1)
    before = [p.detach().clone() for p in params]
    opt.zero_grad()
    layer(torch.ones(4, 3)).sum().backward()
    assert float(opt.grad.abs().sum()) > 0  # backward wrote into the flat buffer
    opt.step(max_norm=10.0)
    assert all(not torch.equal(a, p) for a, p in zip(before, params, strict=True))


def test_flat_adam_refuses_a_replaced_gradient():
    layer = nn.Linear(3, 2)
    opt = FlatAdam(list(layer.parameters()), lr=0.1)
    layer.zero_grad(set_to_none=True)
    layer(torch.ones(4, 3)).sum().backward()
    with pytest.raises(RuntimeError, match="grad was replaced"):
        opt.step(max_norm=1.0)
