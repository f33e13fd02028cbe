"""The training step written out in numpy equals autograd's loss and gradient."""

import numpy as np
import pytest
import torch

from latentsindy._stage_one.coefficient_model import CoefficientModel
from latentsindy._stage_one.estimator import sample_positions
from latentsindy._stage_one.flat_adam import FlatAdam
from latentsindy._stage_one.loss import loss_terms, total_loss
from latentsindy._stage_one.numpy_step import NumpyStep, supported
from latentsindy.generators.timevae import TimeVAE, TimeVAEOptions


def _problem(n_traj=1, n_times=700, irregular=False, seed=0, n_knots=64, kernel_size=5):
    """A random timeVAE (non-zero output) inside a coefficient model, and normalised
    data: two states, four library terms, a pinned constant and a pruned term."""
    gen_ = torch.Generator().manual_seed(seed)
    rand = lambda *s: torch.randn(*s, generator=gen_)  # noqa: E731
    t = np.sort(np.random.default_rng(seed).uniform(0, 10, n_times)) if irregular else None
    gen = TimeVAE(n_inputs=4, n_outputs=8,
                  options=TimeVAEOptions(n_knots=n_knots, kernel_size=kernel_size))
    with torch.no_grad():
        for p in gen.parameters():
            p.copy_(0.3 * rand(*p.shape))
        # a dead channel: its GELU outputs are all exactly zero, so is their spread
        gen.encoder[4].weight[0] = 0.0
        gen.encoder[4].bias[0] = -50.0
    gen.allocate(n_times, None if t is None else sample_positions(t, "cpu"))
    support = torch.ones(2, 4, dtype=torch.bool)
    support[1, 3] = False
    model = CoefficientModel(gen, rand(2, 4), support, torch.ones(2, 4))
    model.pin_constant(0, 1, 0.7)
    theta, xdot = rand(n_traj, n_times, 4), rand(n_traj, n_times, 2)
    weights = 0.5 + torch.rand(n_traj, n_times, 2, generator=gen_)
    inputs = rand(n_traj, 4, n_times)
    return model, (theta, xdot, weights, inputs, 0.02, 0.05, torch.tensor([True, False]))


def _autograd(model, data, l1_weight, rough_weight, rough_scaled, opt):
    theta, xdot, weights, inputs, noise_var, threshold, free = data
    torch.manual_seed(3)
    terms = loss_terms(model, theta, xdot, weights, inputs, noise_var, threshold,
                       free.to(theta.dtype))
    loss = total_loss(terms, l1_weight, rough_weight, 1.0, rough_scaled)
    opt.zero_grad()
    loss.backward()
    return ({k: float(v.detach()) if torch.is_tensor(v) else v for k, v in terms.items()},
            float(loss.detach()), opt.grad.clone())


@pytest.mark.parametrize("n_traj, irregular, fit, shape", [
    (1, False, True, {}), (2, False, True, {}), (1, True, True, {}), (1, False, False, {}),
    (1, True, False, {}),
    # no upsampling layer, a series shorter than the encoder's points, another kernel
    (1, False, True, {"n_knots": 32, "kernel_size": 3}),
    (2, True, True, {"n_knots": 128, "n_times": 90}),
    # a uniform grid with fewer than two samples per knot interval: the samples' loss
    (1, False, True, {"n_knots": 256, "n_times": 300})])
@pytest.mark.parametrize("phase", [1, 2])
def test_loss_and_gradient_equal_autograd(n_traj, irregular, fit, shape, phase):
    """Every tensor's gradient; without the data misfit (``fit`` False: zero weights)
    the penalties' own gradients are compared, which the misfit's would swamp."""
    model, data = _problem(n_traj, irregular=irregular, **shape)
    if not fit:
        data = (data[0], data[1], 0.0 * data[2], *data[3:])
    assert supported(model, data[0])
    opt = FlatAdam([p for p in model.parameters() if p.requires_grad], lr=1e-3)
    l1_weight, rough_weight = (0.1, 0.3) if phase == 1 else (0.0, 2.0)
    terms, loss, grad = _autograd(model, data, l1_weight, rough_weight, phase == 2, opt)
    step = NumpyStep(model, *data)
    n_times, n_knots = shape.get("n_times", 700), shape.get("n_knots", 64)
    assert (step.on_knots is not None) == (not irregular and n_times - 1 >= 2 * (n_knots - 1))
    torch.manual_seed(3)  # the same latent noise
    opt.grad.fill_(float("nan"))  # every gradient must be written (none is zeroed)
    ours = step(l1_weight, rough_weight, 1.0, phase == 2)
    our_loss = total_loss(ours, l1_weight, rough_weight, 1.0, phase == 2)
    assert our_loss == pytest.approx(loss, rel=1e-4)  # float32 sums, rounded differently
    for key, value in terms.items():
        assert ours[key] == pytest.approx(value, rel=1e-4, abs=1e-9), key
    offset = 0
    for name, p in model.named_parameters():  # every tensor's gradient, one by one
        n = p.numel()
        ref, got = grad[offset:offset + n], opt.grad[offset:offset + n]
        offset += n
        # within 3e-4 of its own size (float32: the roughness's signs of near-zero
        # differences can round either way), or a millionth of the whole (a sum that
        # cancels to zero, such as a constant's gradient from the roughness alone)
        assert float((got - ref).norm()) <= 3e-4 * float(ref.norm()) + 1e-6 * float(
            grad.norm()), name
    # the pinned constant and the pruned term get no gradient
    assert float(model.constants.grad[0, 1]) == 0.0
    assert float(model.constants.grad[1, 3]) == 0.0
    opt.release()


def test_gradient_check_against_finite_differences():
    """A direction derivative of the loss in float64 arithmetic: the written-out
    gradient is the loss's (not merely equal to autograd's)."""
    model, data = _problem(n_times=300, seed=4)
    params = [p for p in model.parameters() if p.requires_grad]
    opt = FlatAdam(params, lr=1e-3)
    step = NumpyStep(model, *data)
    torch.manual_seed(3)
    step(0.1, 0.3, 1.0, False)
    direction = torch.randn(opt.flat.shape, generator=torch.Generator().manual_seed(1))
    slope = float(opt.grad @ direction)
    h = 1e-3
    values = []
    for sign in (1.0, -1.0):
        with torch.no_grad():
            opt.flat.add_(sign * h * direction)
        torch.manual_seed(3)
        values.append(total_loss(step(0.1, 0.3, 1.0, False), 0.1, 0.3, 1.0, False))
        with torch.no_grad():
            opt.flat.sub_(sign * h * direction)
    assert (values[0] - values[1]) / (2 * h) == pytest.approx(slope, rel=2e-2)
    opt.release()


def test_not_supported_off_the_cpu_float32_timevae():
    model, data = _problem()
    assert not supported(model, data[0].double())
    assert not supported(model, data[0], data[1].double())
    model.constants.requires_grad_(False)  # a frozen parameter gets no .grad to write
    assert not supported(model, data[0])
    model.constants.requires_grad_(True)
    model.generator.encoder_points = None  # a model file of version 1-2 reads every sample
    assert not supported(model, data[0])


def test_a_step_after_a_new_optimiser_is_an_error():
    model, data = _problem()
    params = [p for p in model.parameters() if p.requires_grad]
    opt = FlatAdam(params, lr=1e-3)
    step = NumpyStep(model, *data)
    opt.release()
    opt = FlatAdam(params, lr=1e-3)
    with pytest.raises(RuntimeError, match="new storage"):
        step(0.1, 0.3, 1.0, False)
    opt.release()


@pytest.mark.parametrize("irregular", [False, True])
def test_training_by_hand_follows_autograd(monkeypatch, irregular):
    """A short two-phase training (pruning, the decisions between the phases) by hand
    and with autograd (the GPU's path; here with the compiled Adam) ends at the same
    support and constants: on the knots and, with irregular times, on the samples."""
    import latentsindy._stage_one.numpy_step as numpy_step
    import latentsindy._stage_one.training as training

    def trained(by_hand):
        model, data = _problem(n_times=400, seed=2, irregular=irregular)
        if not by_hand:
            monkeypatch.setattr(numpy_step, "supported", lambda *args: False)
        theta, xdot, weights, inputs, _, threshold, free = data
        options = training.TrainingOptions(support_steps=60, refit_steps=40, prune_every=5)
        torch.manual_seed(0)
        # a small noise variance: the refit's smoothing weight is then below its cap
        history = training.train(model, theta, xdot, weights, inputs, 1e-4, free,
                                 options, False)
        monkeypatch.undo()
        return model, history

    ours, our_history = trained(True)
    ref, history = trained(False)
    assert torch.equal(ours.support, ref.support)
    assert torch.allclose(ours.constants, ref.constants, rtol=1e-4, atol=1e-5)
    assert 0.01 < history[-1]["rough_bayes"] < 1.0
    for ours_k, ref_k in zip(our_history, history, strict=True):  # every step's loss
        assert ours_k["loss"] == pytest.approx(ref_k["loss"], rel=1e-3)
    assert list(our_history[-1]) == list(history[-1])  # the same record, key for key


@pytest.mark.parametrize("irregular, n_times", [(False, 700), (True, 700), (False, 90)])
def test_term_sizes_are_the_models_at_the_latent_mean(irregular, n_times):
    """Pruning's sizes, mean |Xi| over the samples at the latent's mean, equal the torch
    model's (``model(inputs, 0)``), on the knots and on the samples."""
    model, data = _problem(irregular=irregular, n_times=n_times)
    opt = FlatAdam([p for p in model.parameters() if p.requires_grad], lr=1e-3)
    step = NumpyStep(model, *data)
    assert (step.on_knots is None) == (irregular or n_times < 200)
    with torch.no_grad():
        ref = model(data[3], 0)[0][0].abs().mean(dim=0).numpy()
    np.testing.assert_allclose(step.term_sizes(), ref, rtol=2e-5, atol=1e-7)
    opt.release()
    opt = FlatAdam([p for p in model.parameters() if p.requires_grad], lr=1e-3)
    with pytest.raises(RuntimeError, match="new storage"):
        step.term_sizes()
    opt.release()
