"""timeVAE's training loss and its gradient written out: the CPU's step.

On a CPU, a training step of stage one on a few thousand samples is mostly framework
overhead: the autograd engine and a few hundred small torch operations of a few
microseconds each, around kernels that take about a millisecond in all. Here the
same model and loss (:func:`.loss.loss_terms` of a
:class:`.coefficient_model.CoefficientModel` around a
:class:`~latentsindy.generators.timevae.TimeVAE`) are evaluated and differentiated by
hand, in float32 (a few sums in float64), on views of the parameters' own storage:
each layer forward and backward by one compiled call (:mod:`.step_kernels`), the loss
by :class:`.numpy_loss.NumpyLoss`; the gradients are written into each parameter's
``.grad``, and torch's random stream draws the latent noise as before. The arithmetic
is the model's, rounded differently (tests hold the gradients to autograd's); the
model itself stays a torch module (the decisions between phases, sampling and saving
use it as before; pruning reads its terms' sizes from here).

On a uniform grid with at least two samples per knot interval the loss is evaluated
on the decoder's knots (:mod:`.knot_loss`: the same loss, its misfit and roughness
without reading the series at every sample); elsewhere on the samples.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..generators._knots import applies, interpolation, knot_grid
from ..generators.timevae import _BASE, TimeVAE
from . import step_kernels as kernels
from .coefficient_model import CoefficientModel
from .knot_loss import KnotLoss
from .loss import relative_spacing
from .numpy_loss import NumpyLoss, time_mean

_LOGVAR_RANGE = (-12.0, 6.0)  # TimeVAE.encode's clamp


def supported(model, *data) -> bool:
    """Whether :class:`NumpyStep` can train ``model`` on the tensors ``data``: a
    :class:`.coefficient_model.CoefficientModel` around a timeVAE whose encoder reads
    the series at the decoder's resolution, every parameter trained, everything in
    float32 on a CPU. Anything else trains with autograd."""
    tensors = [*model.parameters(), *data]
    return (type(model) is CoefficientModel and type(model.generator) is TimeVAE
            and model.generator.encoder_points is not None
            and all(p.requires_grad for p in model.parameters())
            and all(x.device.type == "cpu" and x.dtype == torch.float32 for x in tensors))


class _Conv:
    """A 1-D convolution (padding k // 2) followed by a GELU, optionally after a linear
    upsampling by two, on ``n_batch`` series of ``n_in`` points: the compiled kernels
    of :mod:`.step_kernels` on buffers made once."""

    def __init__(self, conv, n_in, n_batch, upsample=False):
        weight = conv.weight.detach().numpy()  # views of the parameters' storage
        n_out_ch, n_ch, self.k = weight.shape
        self.w2 = weight.reshape(n_out_ch, n_ch * self.k)
        self.bias = conv.bias.detach().numpy()
        self.grad_w2 = conv.weight.grad.numpy().reshape(self.w2.shape)
        self.grad_b = conv.bias.grad.numpy()
        self.stride, self.pad, self.upsample = conv.stride[0], conv.padding[0], upsample
        length = 2 * n_in if upsample else n_in
        self.n_out = (length + 2 * self.pad - self.k) // self.stride + 1
        f32 = np.float32
        self.padded = np.zeros((n_batch, n_ch, length + 2 * self.pad), f32)  # zero borders
        self.cols = np.empty((n_batch, n_ch * self.k, self.n_out), f32)
        self.pre, self.act, self.slope, self.grad_pre = (
            np.empty((n_batch, n_out_ch, self.n_out), f32) for _ in range(4))
        self.grad_padded = np.empty_like(self.padded)
        self.grad_in = np.empty((n_batch, n_ch, n_in), f32)
        self.no_input = self.grad_in[:0]

    def forward(self, x):
        """The activations (B, O, L_out) of ``x`` (B, C, n_in), C-contiguous: this
        layer's buffer, which its next call overwrites."""
        kernels.conv_gelu(x, self.k, self.stride, self.pad, self.upsample, self.padded,
                          self.cols, self.w2, self.bias, self.pre, self.act, self.slope)
        return self.act

    def backward(self, grad_act, need_input=True):
        """The parameters' gradients (written) and, if ``need_input``, the input's."""
        grad_in = self.grad_in if need_input else self.no_input
        kernels.conv_backward(grad_act, self.slope, self.cols, self.w2, self.grad_w2,
                              self.grad_b, self.k, self.stride, self.pad, self.upsample,
                              self.grad_pre, self.grad_padded, grad_in)
        return grad_in if need_input else None


def _interpolation(gen, n_knots, n_times):
    """Sparse (n_times, n_knots) matrix: the decoder's knots -> the sample times."""
    if gen.positions is None or len(gen.positions) != n_times:
        return interpolation(*knot_grid(n_times, n_knots), n_knots)
    where = gen.positions.numpy().astype(np.float64) * ((n_knots - 1) / max(n_times - 1, 1))
    left = np.clip(np.floor(where).astype(int), 0, n_knots - 2)
    return interpolation(left, where - left, n_knots)


class NumpyStep:
    """The training loss of ``model`` and its gradient, written into the parameters'
    ``.grad`` (which must exist: :class:`.flat_adam.FlatAdam` makes them).

    Parameters are read from their storage at every call, so the optimiser's updates and
    the model's in-place decisions (support, pinned constants) are seen; make a new
    instance when the parameters get new storage (a new optimiser: a call after that is
    an error). The data, the sample positions and the encoder's pooled input are fixed
    at construction.
    """

    def __init__(self, model, theta, xdot, weights, inputs, noise_var, threshold, free_rows):
        gen = model.generator
        self.model, self.gen = model, gen
        theta, xdot, weights = theta.numpy(), xdot.numpy(), weights.numpy()
        n_states, n_features = model.constants.shape
        self.shape = (n_states, n_features)
        with torch.no_grad():
            if inputs.shape[-1] > gen.encoder_points:
                inputs = F.adaptive_avg_pool1d(inputs, gen.encoder_points)
        self.enc_in = np.ascontiguousarray(inputs.numpy())
        (n_traj, _, length), self.enc = self.enc_in.shape, []
        for layer in gen.encoder:
            if isinstance(layer, nn.Conv1d):
                self.enc.append(_Conv(layer, length, n_traj))
                length = self.enc[-1].n_out
        self.ups, length = [], _BASE
        for layer in gen.upsample:
            if isinstance(layer, nn.Conv1d):  # each follows an upsampling by two
                self.ups.append(_Conv(layer, length, 1, upsample=True))
                length *= 2
        hidden = gen.options.hidden
        last = self.enc[-1].act  # the encoder's summary: pooled, centred, 1 / sd
        self.pooled = (np.empty(2 * hidden, np.float32), np.empty_like(last),
                       np.empty(last.shape[:2], np.float32))
        self.grad_pooled = np.empty_like(last)
        self.dense = np.empty((3, hidden * _BASE), np.float32)  # from_latent: pre, act, slope
        n_times = theta.shape[1]
        uniform = gen.positions is None or len(gen.positions) != n_times  # no spacing
        # the loss on the knots where it is the samples' loss (knot_loss.py); else on
        # the samples, read from the knots by a sparse interpolation
        self.on_knots = (KnotLoss(theta, xdot, weights, length)
                         if applies(n_times, length, uniform) else None)
        self.interp = self.interp_t = None
        if self.on_knots is None:
            self.interp, self.interp_t = _interpolation(gen, length, n_times)
        spacing = None
        if gen.spacing is not None:
            spacing = relative_spacing(gen.spacing).numpy().astype(np.float32)
        self.loss = NumpyLoss(theta, xdot, weights, noise_var, threshold, free_rows.numpy(),
                              spacing, self.on_knots)
        self.linears = {name: (m.weight.detach().numpy(), m.bias.detach().numpy(),
                               m.weight.grad.numpy(), m.bias.grad.numpy())
                        for name, m in (("to_latent", gen.to_latent),
                                        ("from_latent", gen.from_latent),
                                        ("to_coefficients", gen.to_coefficients))}
        self.constants = model.constants.detach().numpy()
        self.constants_grad = model.constants.grad.numpy()
        self._grad_owner = model.constants.grad

    def __call__(self, l1_weight, rough_weight, kl_weight, rough_scaled):
        """Loss terms (as :func:`.loss.loss_terms`, floats); the gradient of
        :func:`.loss.total_loss` with these weights is written."""
        self._check_storage()
        mu, logvar, raw_logvar, pooled_parts = self._encode()
        eps = torch.randn((1, *mu.shape), dtype=torch.float32).numpy()[0]
        std = np.exp(0.5 * logvar)
        z = mu + eps * std
        series, decoder_parts = self._decode(z)
        kl = 0.5 * float(np.sum(mu * mu + np.exp(logvar) - 1.0 - logvar))
        terms, grad_series, grad_const, grad_kl = self._loss(
            series, kl, l1_weight, rough_weight, kl_weight, rough_scaled)
        self.constants_grad[...] = grad_const
        grad_z = self._decode_backward(grad_series, decoder_parts)
        c = np.float32(grad_kl)
        grad_mu = grad_z + c * mu
        grad_logvar = grad_z * eps * 0.5 * std + c * 0.5 * (np.exp(logvar) - 1.0)
        grad_logvar *= (raw_logvar >= _LOGVAR_RANGE[0]) & (raw_logvar <= _LOGVAR_RANGE[1])
        self._encode_backward(np.concatenate([grad_mu, grad_logvar]), pooled_parts)
        return terms

    def _check_storage(self):
        if self.model.constants.grad is not self._grad_owner:
            raise RuntimeError("NumpyStep: the parameters' gradients have new storage (a new "
                               "optimiser); make a new NumpyStep for it.")

    # -- encoder ---------------------------------------------------------------------
    def _encode(self):
        h = self.enc_in
        for conv in self.enc:
            h = conv.forward(h)
        pooled, centred, inv = self.pooled
        kernels.pool(h, pooled, centred, inv)
        w, b, _, _ = self.linears["to_latent"]
        out = w @ pooled + b
        half = out.shape[0] // 2
        raw_logvar = out[half:]
        logvar = np.clip(raw_logvar, *_LOGVAR_RANGE)
        return out[:half], logvar, raw_logvar, self.pooled

    def _encode_backward(self, grad_out, pooled_parts):
        pooled, centred, inv = pooled_parts
        w, _, gw, gb = self.linears["to_latent"]
        np.multiply(grad_out[:, None], pooled[None, :], out=gw)
        gb[...] = grad_out
        grad_h = self.grad_pooled
        kernels.pool_backward(w.T @ grad_out, centred, inv, grad_h)
        for k in range(len(self.enc) - 1, -1, -1):
            grad_h = self.enc[k].backward(grad_h, need_input=k > 0)

    # -- decoder ---------------------------------------------------------------------
    def _decode(self, z):
        w, b, _, _ = self.linears["from_latent"]
        pre, act, slope = self.dense
        np.dot(w, z, out=pre)
        pre += b
        kernels.gelu(pre, act, slope)
        h = act.reshape(1, self.gen.options.hidden, -1)
        for conv in self.ups:
            h = conv.forward(h)
        wc, bc, _, _ = self.linears["to_coefficients"]
        knots = wc[:, :, 0] @ h[0] + bc[:, None]  # (n_outputs, n_knots)
        if self.on_knots is not None:
            return knots.T, (z, h[0])  # (n_knots, n_outputs)
        series = np.asarray(self.interp @ knots.T)  # (T, n_outputs)
        return series, (z, h[0])

    def _decode_backward(self, grad_series, decoder_parts):
        z, last = decoder_parts
        wc, _, gwc, gbc = self.linears["to_coefficients"]
        if self.on_knots is not None:
            grad_knots = np.ascontiguousarray(grad_series.T)  # (n_outputs, n_knots)
        else:
            grad_knots = np.asarray(self.interp_t @ grad_series).T
        gwc[:, :, 0] = grad_knots @ last.T
        gbc[...] = grad_knots.sum(axis=1)
        grad_h = (wc[:, :, 0].T @ grad_knots)[None]
        for conv in reversed(self.ups):
            grad_h = conv.backward(grad_h)
        grad_a = grad_h.reshape(-1) * self.dense[2]
        w, _, gw, gb = self.linears["from_latent"]
        np.multiply(grad_a[:, None], z[None, :], out=gw)
        gb[...] = grad_a
        return w.T @ grad_a

    # -- loss ------------------------------------------------------------------------
    def _coefficients(self, series):
        """The model's coefficients from the generator's ``series`` (T or K, n F), with
        the support (as numbers), the varying mask and the pinned mask."""
        model = self.model
        support = model.support.numpy().astype(np.float32)
        varying = model.time_varying.numpy()
        pinned = model.pin_mask.numpy()
        const = np.where(pinned, model.pin_value.numpy(), self.constants)
        # (T, n, F) on the samples, (n_knots, n, F) on the knots; in the model's order of
        # operations (the samples' second differences cancel: a different rounding shows)
        xi = support * (const + varying * series.reshape(-1, *self.shape))
        return xi, support, varying, pinned

    def term_sizes(self):
        """``mean_t |xi_t|`` per term (n, F) of the posterior mean (the latent at its
        mean), as pruning reads it, at the parameters' current values."""
        self._check_storage()
        mu = self._encode()[0]
        xi = self._coefficients(self._decode(mu)[0])[0]
        if self.on_knots is not None:
            return self.on_knots.magnitude(xi)[0]
        return time_mean(np.abs(xi))

    def _loss(self, series, kl, l1_weight, rough_weight, kl_weight, rough_scaled):
        """The loss of the model's coefficients (:class:`.numpy_loss.NumpyLoss`), and its
        gradient by the generator's series and by the constants."""
        xi, support, varying, pinned = self._coefficients(series)
        mask = support * varying
        terms, grad_xi, grad_kl = self.loss(xi, support, kl, l1_weight, rough_weight,
                                            kl_weight, rough_scaled)
        grad_series = (grad_xi * mask).reshape(xi.shape[0], -1)
        # sum_t dL/dxi_t, which on the knots is their sum (each sample's weights sum to 1)
        grad_const = np.where(pinned, 0.0, time_mean(grad_xi) * (xi.shape[0] * support))
        return terms, grad_series, grad_const, grad_kl
