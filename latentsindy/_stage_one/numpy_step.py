"""timeVAE's training loss and its gradient in numpy, written out: the CPU's step.

On a CPU, a training step of stage one on a few thousand samples is mostly framework
overhead: the autograd engine and a few hundred small torch operations of a few
microseconds each, around kernels that take about a millisecond in all. Here the
same model and loss (:func:`.loss.loss_terms` of a
:class:`.coefficient_model.CoefficientModel` around a
:class:`~latentsindy.generators.timevae.TimeVAE`) are evaluated and differentiated by
hand in numpy (the loss by :class:`.numpy_loss.NumpyLoss`), in float32, on views of the
parameters' own storage: the gradients are written into each parameter's ``.grad``, the
optimiser is unchanged, and torch's random stream draws the latent noise as before. The
arithmetic is the model's, rounded differently (a test holds the gradients to
autograd's); the model itself stays a torch module (pruning, the decisions between
phases, sampling and saving use it as before).

The convolutions run as matrix products over unrolled windows; the exact GELU's error
function is torch's (vectorised), on the same memory. On a uniform grid with at least
two samples per knot interval the loss is evaluated on the decoder's knots
(:mod:`.knot_loss`: the same loss, its misfit and roughness without reading the series
at every sample); elsewhere on the samples.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from ..generators._knots import applies, interpolation, knot_grid
from ..generators.timevae import _BASE, TimeVAE
from .coefficient_model import CoefficientModel
from .knot_loss import KnotLoss
from .loss import relative_spacing
from .numpy_loss import NumpyLoss, time_mean

_INV_SQRT2 = np.float32(1.0 / math.sqrt(2.0))
_INV_SQRT_2PI = np.float32(1.0 / math.sqrt(2.0 * math.pi))
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


def _gelu(x):
    """GELU (erf form) and its derivative at ``x``."""
    phi = 0.5 * (1.0 + torch.erf(torch.from_numpy(x * _INV_SQRT2)).numpy())
    slope = phi + x * _INV_SQRT_2PI * np.exp(-0.5 * x * x)
    return x * phi, slope


class _Conv:
    """A 1-D convolution (padding k // 2) as a product over unrolled windows."""

    def __init__(self, conv, n_in):
        self.weight = conv.weight.detach().numpy()
        self.bias = conv.bias.detach().numpy()
        self.stride = conv.stride[0]
        self.pad = conv.padding[0]
        self.k = conv.kernel_size[0]
        self.n_in = n_in
        self.n_out = (n_in + 2 * self.pad - self.k) // self.stride + 1
        self.grads = (conv.weight.grad.numpy(), conv.bias.grad.numpy())
        self.padded = self.cols = None  # buffers, made at the first call

    def forward(self, x):
        batch, channels, _ = x.shape
        if self.padded is None or self.padded.shape[0] != batch:
            self.padded = np.zeros((batch, channels, self.n_in + 2 * self.pad), np.float32)
            self.cols = np.empty((batch, channels, self.k, self.n_out), np.float32)
        self.padded[:, :, self.pad:self.pad + self.n_in] = x  # the borders stay zero
        span = self.stride * (self.n_out - 1) + 1
        for tap in range(self.k):  # (B, C * k, L): channel-major, tap-minor, as the weight
            self.cols[:, :, tap] = self.padded[:, :, tap:tap + span:self.stride]
        cols = self.cols.reshape(batch, channels * self.k, self.n_out)
        w2 = self.weight.reshape(self.weight.shape[0], -1)
        if batch == 1:  # a plain matrix product: numpy's stacked one costs more
            return (w2 @ cols[0] + self.bias[:, None])[None]
        return np.matmul(w2, cols) + self.bias[:, None]

    def backward(self, grad_out, need_input=True):
        grad_w, grad_b = self.grads
        w2 = self.weight.reshape(self.weight.shape[0], -1)
        batch, channels = grad_out.shape[0], self.weight.shape[1]
        cols = self.cols.reshape(batch, channels * self.k, self.n_out)
        if batch == 1:
            grad_w.reshape(w2.shape)[...] = grad_out[0] @ cols[0].T
        else:
            grad_w.reshape(w2.shape)[...] = np.matmul(grad_out, cols.transpose(0, 2, 1)).sum(0)
        grad_b[...] = grad_out.sum(axis=(0, 2))
        if not need_input:
            return None
        cols = np.matmul(w2.T, grad_out).reshape(batch, channels, self.k, self.n_out)
        padded = np.zeros((batch, channels, self.n_in + 2 * self.pad), dtype=np.float32)
        span = self.stride * (self.n_out - 1) + 1
        for tap in range(self.k):
            padded[:, :, tap:tap + span:self.stride] += cols[:, :, tap]
        return padded[:, :, self.pad:self.pad + self.n_in]


def _upsample(x):
    """Linear upsampling by two (align_corners=False) along the last axis."""
    out = np.empty((*x.shape[:-1], 2 * x.shape[-1]), dtype=np.float32)
    out[..., 0], out[..., -1] = x[..., 0], x[..., -1]
    out[..., 2::2] = 0.25 * x[..., :-1] + 0.75 * x[..., 1:]
    out[..., 1:-1:2] = 0.75 * x[..., :-1] + 0.25 * x[..., 1:]
    return out


def _upsample_backward(grad):
    """The gradient of :func:`_upsample` by its input."""
    even, odd = grad[..., 2::2], grad[..., 1:-1:2]
    out = np.zeros((*grad.shape[:-1], grad.shape[-1] // 2), dtype=np.float32)
    out[..., 0] += grad[..., 0]
    out[..., -1] += grad[..., -1]
    out[..., :-1] += 0.25 * even + 0.75 * odd
    out[..., 1:] += 0.75 * even + 0.25 * odd
    return out


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
        length, self.enc = self.enc_in.shape[-1], []
        for layer in gen.encoder:
            if isinstance(layer, nn.Conv1d):
                self.enc.append(_Conv(layer, length))
                length = self.enc[-1].n_out
        self.ups, length = [], _BASE
        for layer in gen.upsample:
            if isinstance(layer, nn.Conv1d):
                length *= 2  # each follows an upsampling by two
                self.ups.append(_Conv(layer, length))
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
        if self.model.constants.grad is not self._grad_owner:
            raise RuntimeError("NumpyStep: the parameters' gradients have new storage (a new "
                               "optimiser); make a new NumpyStep for it.")
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

    # -- encoder ---------------------------------------------------------------------
    def _encode(self):
        h, parts = self.enc_in, []
        for conv in self.enc:
            a = conv.forward(h)
            h, slope = _gelu(a)
            parts.append(slope)
        mean = h.mean(axis=2)
        centred = h - mean[:, :, None]
        std = np.sqrt((centred * centred).sum(axis=2) / (h.shape[2] - 1))
        pooled = np.concatenate([mean, std], axis=1).mean(axis=0)
        w, b, _, _ = self.linears["to_latent"]
        out = w @ pooled + b
        half = out.shape[0] // 2
        raw_logvar = out[half:]
        logvar = np.clip(raw_logvar, *_LOGVAR_RANGE)
        return out[:half], logvar, raw_logvar, (parts, pooled, centred, std)

    def _encode_backward(self, grad_out, pooled_parts):
        parts, pooled, centred, std = pooled_parts
        w, _, gw, gb = self.linears["to_latent"]
        gw[...] = np.outer(grad_out, pooled)
        gb[...] = grad_out
        grad_pooled = (w.T @ grad_out) / centred.shape[0]
        hidden = centred.shape[1]
        length = centred.shape[2]
        # a channel with no spread (a dead GELU: every output exactly 0) gets no
        # gradient through its standard deviation, as in torch's std backward
        inv = np.divide(1.0, (length - 1) * std, out=np.zeros_like(std), where=std > 0)
        grad_h = (grad_pooled[None, :hidden, None] / length
                  + grad_pooled[None, hidden:, None] * centred * inv[:, :, None])
        for k in range(len(self.enc) - 1, -1, -1):
            grad_h = self.enc[k].backward(grad_h * parts[k], need_input=k > 0)

    # -- decoder ---------------------------------------------------------------------
    def _decode(self, z):
        w, b, _, _ = self.linears["from_latent"]
        a = w @ z + b
        h, slope0 = _gelu(a)
        h = h.reshape(1, self.gen.options.hidden, -1)
        parts = [(z, slope0)]
        for conv in self.ups:
            up = _upsample(h)
            h, slope = _gelu(conv.forward(up))
            parts.append(slope)
        wc, bc, _, _ = self.linears["to_coefficients"]
        knots = wc[:, :, 0] @ h[0] + bc[:, None]  # (n_outputs, n_knots)
        if self.on_knots is not None:
            return knots.T, (parts, h[0])  # (n_knots, n_outputs)
        series = np.asarray(self.interp @ knots.T)  # (T, n_outputs)
        return series, (parts, h[0])

    def _decode_backward(self, grad_series, decoder_parts):
        parts, last = decoder_parts
        wc, _, gwc, gbc = self.linears["to_coefficients"]
        if self.on_knots is not None:
            grad_knots = np.ascontiguousarray(grad_series.T)  # (n_outputs, n_knots)
        else:
            grad_knots = np.asarray(self.interp_t @ grad_series).T
        gwc[:, :, 0] = grad_knots @ last.T
        gbc[...] = grad_knots.sum(axis=1)
        grad_h = (wc[:, :, 0].T @ grad_knots)[None]
        for k in range(len(self.ups) - 1, -1, -1):
            grad_up = self.ups[k].backward(grad_h * parts[k + 1])
            grad_h = _upsample_backward(grad_up)
        z, slope0 = parts[0]
        grad_a = grad_h.reshape(-1) * slope0
        w, _, gw, gb = self.linears["from_latent"]
        gw[...] = np.outer(grad_a, z)
        gb[...] = grad_a
        return w.T @ grad_a

    # -- loss ------------------------------------------------------------------------
    def _loss(self, series, kl, l1_weight, rough_weight, kl_weight, rough_scaled):
        """The loss of the model's coefficients (:class:`.numpy_loss.NumpyLoss`), and its
        gradient by the generator's series and by the constants."""
        model = self.model
        n_states, n_features = self.shape
        support = model.support.numpy().astype(np.float32)
        varying = model.time_varying.numpy()
        pinned = model.pin_mask.numpy()
        const = np.where(pinned, model.pin_value.numpy(), self.constants)
        mask = support * varying
        # (T, n, F) on the samples, (n_knots, n, F) on the knots; in the model's order of
        # operations (the samples' second differences cancel: a different rounding shows)
        xi = support * (const + varying * series.reshape(-1, n_states, n_features))
        terms, grad_xi, grad_kl = self.loss(xi, support, kl, l1_weight, rough_weight,
                                            kl_weight, rough_scaled)
        grad_series = (grad_xi * mask).reshape(xi.shape[0], -1)
        # sum_t dL/dxi_t, which on the knots is their sum (each sample's weights sum to 1)
        grad_const = np.where(pinned, 0.0, time_mean(grad_xi) * (xi.shape[0] * support))
        return terms, grad_series, grad_const, grad_kl
