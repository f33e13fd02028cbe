"""The compiled pieces of the training step against torch's float64 layers and autograd."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from latentsindy._stage_one import step_kernels as kernels


def test_gelu_and_its_slope_within_float32_rounding_of_the_exact_erf():
    """Abramowitz-Stegun 7.1.26 has absolute error below 1.5e-7 in erf: the GELU and its
    slope are within 5e-7 (times 1 + |x|) of float64's exact ones, as torch's float32
    GELU is; far out, the tails are exactly 0 and x."""
    x = np.concatenate([np.linspace(-12, 12, 4001), [-40.0, 0.0, 40.0]]).astype(np.float32)
    act, slope = np.empty_like(x), np.empty_like(x)
    kernels.gelu(x, act, slope)
    exact = torch.tensor(x, dtype=torch.float64, requires_grad=True)
    value = F.gelu(exact)
    value.sum().backward()
    tolerance = 5e-7 * (1 + np.abs(x))
    assert np.all(np.abs(act - value.detach().numpy()) <= tolerance)
    assert np.all(np.abs(slope - exact.grad.numpy()) <= tolerance)
    assert act[-3] == 0.0 and act[-1] == 40.0 and act[-2] == 0.0
    assert slope[-3] == 0.0 and slope[-1] == 1.0 and slope[-2] == pytest.approx(0.5, abs=1e-7)


@pytest.mark.parametrize("n_batch, n_ch, n_in, stride, upsample", [
    (1, 32, 32, 1, True), (2, 3, 64, 2, False), (1, 8, 17, 2, False), (2, 5, 9, 1, True)])
def test_convolution_forward_and_backward_equal_torch(n_batch, n_ch, n_in, stride, upsample):
    """One layer (optional upsampling by two, convolution with padding k // 2, GELU):
    the activations and the gradients by the weight, the bias and the input, against
    torch in float64."""
    rng = np.random.default_rng(0)
    k, pad, n_out_ch = 5, 2, 6
    x = rng.standard_normal((n_batch, n_ch, n_in)).astype(np.float32)
    w = (0.3 * rng.standard_normal((n_out_ch, n_ch, k))).astype(np.float32)
    b = rng.standard_normal(n_out_ch).astype(np.float32)
    xt, wt, bt = (torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in (x, w, b))
    up = F.interpolate(xt, scale_factor=2, mode="linear", align_corners=False) if upsample else xt
    ref = F.gelu(F.conv1d(up, wt, bt, stride=stride, padding=pad))
    grad_act_shape = ref.shape
    grad_act = rng.standard_normal(grad_act_shape).astype(np.float32)
    (ref * torch.tensor(grad_act, dtype=torch.float64)).sum().backward()

    length = 2 * n_in if upsample else n_in
    n_out = grad_act_shape[-1]
    f32 = np.float32
    padded = np.zeros((n_batch, n_ch, length + 2 * pad), f32)
    cols = np.empty((n_batch, n_ch * k, n_out), f32)
    pre, act, slope, grad_pre = (np.empty((n_batch, n_out_ch, n_out), f32) for _ in range(4))
    w2 = w.reshape(n_out_ch, -1)
    kernels.conv_gelu(x, k, stride, pad, upsample, padded, cols, w2, b, pre, act, slope)
    np.testing.assert_allclose(act, ref.detach().numpy(), rtol=1e-5, atol=1e-5)

    grad_w2, grad_b = np.empty_like(w2), np.empty_like(b)
    grad_in = np.full((n_batch, n_ch, n_in), np.nan, f32)  # every entry must be written
    kernels.conv_backward(grad_act, slope, cols, w2, grad_w2, grad_b, k, stride, pad,
                          upsample, grad_pre, np.empty_like(padded), grad_in)
    scale = lambda t: 1e-5 * float(t.abs().max())  # noqa: E731  (float32 sums of ~100 terms)
    np.testing.assert_allclose(grad_w2.reshape(w.shape), wt.grad.numpy(), atol=scale(wt.grad))
    np.testing.assert_allclose(grad_b, bt.grad.numpy(), atol=scale(bt.grad))
    np.testing.assert_allclose(grad_in, xt.grad.numpy(), atol=scale(xt.grad))


def test_encoder_summary_and_its_gradient_equal_torch():
    """Mean and standard deviation over time, averaged over the series; a channel with
    no spread gets no gradient through its deviation (as torch's std backward, which
    masks it to zero)."""
    rng = np.random.default_rng(1)
    h = rng.standard_normal((2, 4, 16)).astype(np.float32)
    h[:, 3] = 0.0  # a dead channel
    pooled, centred, inv = np.empty(8, np.float32), np.empty_like(h), np.empty((2, 4), np.float32)
    kernels.pool(h, pooled, centred, inv)
    ht = torch.tensor(h, dtype=torch.float64, requires_grad=True)
    ref = torch.cat([ht.mean(dim=-1), ht.std(dim=-1)], dim=-1).mean(dim=0)
    np.testing.assert_allclose(pooled, ref.detach().numpy(), rtol=1e-6, atol=1e-7)
    grad_pooled = rng.standard_normal(8).astype(np.float32)  # the dead channel's too
    (ref * torch.tensor(grad_pooled, dtype=torch.float64)).sum().backward()
    grad_h = np.full_like(h, np.nan)
    kernels.pool_backward(grad_pooled, centred, inv, grad_h)
    np.testing.assert_allclose(grad_h, ht.grad.numpy(), rtol=1e-5, atol=1e-7)
    assert np.all(inv[:, 3] == 0.0)


def test_adam_returns_the_norm_and_clips_only_above_it():
    flat = np.zeros(4, np.float32)
    grad = np.array([3.0, 4.0, 0.0, 0.0], np.float32)
    exp_avg, exp_avg_sq = np.zeros(4, np.float32), np.zeros(4, np.float32)
    norm = kernels.adam(flat, grad, exp_avg, exp_avg_sq, 1.0, 0.1, 0.9, 0.999, 1e-8, 1)
    assert norm == pytest.approx(5.0)
    np.testing.assert_allclose(grad, [0.6, 0.8, 0.0, 0.0], rtol=1e-6)  # clipped to norm 1
    # the first step of Adam moves every parameter with a gradient by the learning rate
    np.testing.assert_allclose(flat, [-0.1, -0.1, 0.0, 0.0], rtol=1e-5)
    grad[:] = [0.3, 0.0, 0.0, 0.0]
    kernels.adam(flat, grad, exp_avg, exp_avg_sq, 1.0, 0.1, 0.9, 0.999, 1e-8, 2)
    assert grad[0] == np.float32(0.3)  # below the norm: not scaled
