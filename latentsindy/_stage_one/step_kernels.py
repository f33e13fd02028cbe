"""The training step's pieces, compiled (numba): each layer forward or backward in one call.

Written in numpy, a layer of the timeVAE is a dozen array operations of a few
microseconds each around one matrix product: on prey-only Lotka-Volterra (64 knots,
32 channels) the network's forward and backward took 0.44 ms of a 0.71 ms step, most of
it fixed costs. Here each layer is one compiled call: the windows unrolled by loops, the
product by the BLAS (numba's ``np.dot``: a direct loop over a 32 x 32 x 5 convolution
was ten times slower), the bias and the GELU fused into one pass; the encoder's
summary (:func:`pool`) is one more. Adam with the gradient clipping is one loop over
the flat buffers (:func:`adam`), and the loss's misfit, magnitude and roughness on the
decoder's knots (:class:`.knot_loss.KnotLoss`'s arrays) one call each. Together they
took the step from 0.71 to about 0.25 ms.

The arithmetic is the written-out step's in float32 (some sums accumulated in
float64), rounded differently (the BLAS's sums in their own order, erf as torch's
vectorised CPU erf computes it); tests hold the gradients to autograd's, each layer to
torch's in float64 and Adam to torch's. Every array passed in is C-contiguous (the
products' operands then need no copies) and written in place. ``error_model="numpy"``:
a division by zero gives inf or nan, not an exception, so the element-wise loops
vectorise (Adam's took 55 us, then 5).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_F32 = np.float32
_INV_SQRT2 = _F32(1.0 / math.sqrt(2.0))
_INV_SQRT_2PI = _F32(1.0 / math.sqrt(2.0 * math.pi))
_HALF = _F32(0.5)
_ONE = _F32(1.0)
# erf by Abramowitz and Stegun 7.1.26 (absolute error below 1.5e-7), as torch's own
# vectorised CPU erf: one exp, shared with the GELU's slope, and no branches on the
# argument's size (the C library's erf with its own exp took 2-5 times as long)
_P = _F32(0.3275911)
_A = (_F32(0.254829592), _F32(-0.284496736), _F32(1.421413741), _F32(-1.453152027),
      _F32(1.061405429))


@njit(cache=True, nogil=True, error_model="numpy")
def gelu(a, act, slope):
    """GELU (erf form) of ``a`` into ``act``, its derivative into ``slope`` (any shape,
    C-contiguous): within 5e-7 (1 + |a|) of float64's, as torch's float32 GELU."""
    x, y, s = a.reshape(-1), act.reshape(-1), slope.reshape(-1)
    a1, a2, a3, a4, a5 = _A
    for i in range(x.shape[0]):
        v = x[i]
        w = v * _INV_SQRT2
        t = _ONE / (_ONE + _P * abs(w))
        bell = math.exp(-w * w)  # exp(-v^2 / 2)
        erf = _ONE - ((((a5 * t + a4) * t + a3) * t + a2) * t + a1) * t * bell
        phi = _HALF * (_ONE - erf) if w < 0 else _HALF * (_ONE + erf)
        y[i] = v * phi
        s[i] = phi + v * _INV_SQRT_2PI * bell


@njit(cache=True, nogil=True, error_model="numpy")
def unroll(x, k, stride, pad, upsample, padded, cols):
    """The windows of a 1-D convolution (padding ``pad``) of ``x`` (B, C, L), or of its
    linear upsampling by two (``upsample``: align_corners False), into ``cols``
    (B, C k, L_out): channel-major, tap-minor, as the weight's rows. ``padded``
    (B, C, L' + 2 pad), whose borders must be zero, holds the (upsampled) input."""
    n_batch, n_ch, n_in = x.shape
    n_out = cols.shape[2]
    for b in range(n_batch):
        for c in range(n_ch):
            row = padded[b, c]
            if upsample:
                row[pad] = x[b, c, 0]
                row[pad + 2 * n_in - 1] = x[b, c, n_in - 1]
                for i in range(n_in - 1):
                    lo, hi = x[b, c, i], x[b, c, i + 1]
                    row[pad + 2 * i + 1] = _F32(0.75) * lo + _F32(0.25) * hi
                    row[pad + 2 * i + 2] = _F32(0.25) * lo + _F32(0.75) * hi
            else:
                for i in range(n_in):
                    row[pad + i] = x[b, c, i]
            for tap in range(k):
                out = cols[b, c * k + tap]
                for j in range(n_out):
                    out[j] = row[tap + stride * j]


@njit(cache=True, nogil=True, error_model="numpy")
def conv_gelu(x, k, stride, pad, upsample, padded, cols, w2, bias, pre, act, slope):
    """A convolution of ``x`` by ``w2`` (O, C k) plus ``bias``, through the windows of
    :func:`unroll` (its arguments), into ``pre`` (B, O, L_out); its GELU into ``act``,
    the GELU's slope into ``slope``."""
    unroll(x, k, stride, pad, upsample, padded, cols)
    for b in range(cols.shape[0]):
        pre[b] = np.dot(w2, cols[b])
        for o in range(pre.shape[1]):
            row = pre[b, o]
            for j in range(row.shape[0]):
                row[j] += bias[o]
    gelu(pre, act, slope)


@njit(cache=True, nogil=True, error_model="numpy")
def conv_backward(grad_act, slope, cols, w2, grad_w2, grad_b, k, stride, pad, upsample,
                  grad_pre, grad_padded, grad_in):
    """The backward of :func:`conv_gelu`: from the gradient by the
    activations ``grad_act`` (B, O, L_out), the weight's and bias's gradients (written),
    and, unless ``grad_in`` is empty (shape 0 on its first axis), the input's: through
    the windows back to ``x`` (B, C, L) of :func:`unroll` (through the upsampling where
    ``upsample``). ``grad_pre`` and ``grad_padded`` are workspaces."""
    n_batch, n_out_ch, n_out = grad_act.shape
    for b in range(n_batch):
        for o in range(n_out_ch):
            for j in range(n_out):
                grad_pre[b, o, j] = grad_act[b, o, j] * slope[b, o, j]
    grad_w2[...] = np.dot(grad_pre[0], cols[0].T)
    for b in range(1, n_batch):
        grad_w2 += np.dot(grad_pre[b], cols[b].T)
    for o in range(n_out_ch):
        total = _F32(0.0)
        for b in range(n_batch):
            for j in range(n_out):
                total += grad_pre[b, o, j]
        grad_b[o] = total
    if grad_in.shape[0] == 0:
        return
    n_ch, n_in = grad_in.shape[1], grad_in.shape[2]
    for b in range(n_batch):
        grad_cols = np.dot(w2.T, grad_pre[b])  # (C k, L_out)
        row = grad_padded[b]
        row[...] = 0.0
        for c in range(n_ch):
            for tap in range(k):
                g = grad_cols[c * k + tap]
                for j in range(n_out):
                    row[c, tap + stride * j] += g[j]
        for c in range(n_ch):
            g = row[c, pad:]
            if upsample:  # the upsampling's transpose: each input feeds four outputs
                out = grad_in[b, c]
                out[...] = 0.0
                out[0] += g[0]
                out[n_in - 1] += g[2 * n_in - 1]
                for i in range(n_in - 1):
                    odd, even = g[2 * i + 1], g[2 * i + 2]
                    out[i] += _F32(0.75) * odd + _F32(0.25) * even
                    out[i + 1] += _F32(0.25) * odd + _F32(0.75) * even
            else:
                for i in range(n_in):
                    grad_in[b, c, i] = g[i]


@njit(cache=True, nogil=True, error_model="numpy")
def pool(h, pooled, centred, inv):
    """The encoder's summary of ``h`` (B, C, L): each channel's mean and standard
    deviation (n - 1) over time, averaged over the series, into ``pooled`` (2 C,); for
    the backward, ``centred`` (h minus its mean) and ``inv`` (B, C): 1 / ((L - 1) sd),
    0 where a channel has no spread (a dead GELU: torch's std backward gives it no
    gradient)."""
    n_batch, n_ch, length = h.shape
    pooled[...] = 0.0
    for b in range(n_batch):
        for c in range(n_ch):
            total = 0.0
            for j in range(length):
                total += h[b, c, j]
            mean = h.dtype.type(total / length)
            squares = 0.0
            for j in range(length):
                d = h[b, c, j] - mean
                centred[b, c, j] = d
                squares += d * d
            sd = h.dtype.type(math.sqrt(squares / (length - 1)))
            inv[b, c] = 1.0 / ((length - 1) * sd) if sd > 0 else 0.0
            pooled[c] += mean / n_batch
            pooled[n_ch + c] += sd / n_batch


@njit(cache=True, nogil=True, error_model="numpy")
def pool_backward(grad_pooled, centred, inv, grad_h):
    """The gradient by ``h`` of :func:`pool`, from the gradient by ``pooled``."""
    n_batch, n_ch, length = centred.shape
    for c in range(n_ch):
        by_mean = grad_pooled[c] / (n_batch * length)
        by_sd = grad_pooled[n_ch + c] / n_batch
        for b in range(n_batch):
            scale = by_sd * inv[b, c]
            for j in range(length):
                grad_h[b, c, j] = by_mean + scale * centred[b, c, j]


@njit(cache=True, nogil=True, error_model="numpy")
def adam(flat, grad, exp_avg, exp_avg_sq, max_norm, lr, beta1, beta2, eps, step):
    """Clip ``grad`` to total 2-norm ``max_norm`` (in place), then one Adam step of
    ``flat`` (torch.optim.Adam's update, no weight decay) with the moments in place;
    ``step`` counts from 1. Returns the gradient's norm before clipping."""
    norm = math.sqrt(float(np.dot(grad, grad)))
    scale = _F32(min(max_norm / (norm + 1e-6), 1.0))
    w1, b2, w2 = _F32(1.0 - beta1), _F32(beta2), _F32(1.0 - beta2)
    bias2_sqrt = _F32(math.sqrt(1.0 - beta2**step))
    step_size = _F32(lr / (1.0 - beta1**step))
    e = _F32(eps)
    for i in range(flat.shape[0]):
        g = grad[i] * scale
        grad[i] = g
        m = exp_avg[i] + w1 * (g - exp_avg[i])
        v = exp_avg_sq[i] * b2 + w2 * (g * g)
        exp_avg[i] = m
        exp_avg_sq[i] = v
        flat[i] -= step_size * (m / (math.sqrt(v) / bias2_sqrt + e))
    return norm


# -- the loss on the knots (knot_loss.KnotLoss: its arrays, its definitions) ------------

@njit(cache=True, nogil=True, error_model="numpy")
def _sign(x):
    return (x > 0) - (x < 0)


@njit(cache=True, nogil=True, error_model="numpy")
def quadratic_form(indptr, indices, data, cross, x, g):
    """``g = G x - c`` for ``G`` in CSR (``indptr``, ``indices``, ``data``) and ``c``
    ``cross``; returns ``x' g - c' x`` (float64 throughout)."""
    value = 0.0
    for row in range(x.shape[0]):
        total = 0.0
        for at in range(indptr[row], indptr[row + 1]):
            total += data[at] * x[indices[at]]
        g[row] = total - cross[row]
        value += x[row] * g[row] - cross[row] * x[row]
    return value


@njit(cache=True, nogil=True, error_model="numpy")
def knot_roughness(xi, inside, inside64, u, v, a, b, c1, c2, value, grad, g_diff):
    """:meth:`.knot_loss.KnotLoss.roughness` of the knots ``xi`` (K, m): ``value`` (m,)
    and ``grad`` (K, m) written; ``g_diff`` (K - 1, m) is a workspace."""
    n_knots, m = xi.shape
    f1, f2 = xi.dtype.type(c1), xi.dtype.type(c2)
    for r in range(m):
        second = first = 0.0
        for k in range(n_knots - 1):
            d = xi[k + 1, r] - xi[k, r]
            first += abs(d) * inside64[k]
            g_diff[k, r] = f1 * inside[k] * _sign(d)
        for j in range(n_knots - 2):  # at knot j + 1: d_j before it, d_{j+1} after it
            before, after = xi[j + 1, r] - xi[j, r], xi[j + 2, r] - xi[j + 1, r]
            on_before = on_after = xi.dtype.type(0.0)
            for s in range(a.shape[0]):
                curve = a[s, j] * before + b[s, j] * after
                second += abs(curve)
                sign = _sign(curve)
                on_before += a[s, j] * sign
                on_after += b[s, j] * sign
            across = u[j] * before + v[j] * after
            first += abs(across)
            sign = _sign(across)
            g_diff[j, r] += f2 * on_before + f1 * u[j] * sign
            g_diff[j + 1, r] += f2 * on_after + f1 * v[j] * sign
        value[r] = c2 * second + c1 * first
        grad[0, r] = -g_diff[0, r]
        for k in range(1, n_knots - 1):
            grad[k, r] = g_diff[k - 1, r] - g_diff[k, r]
        grad[n_knots - 1, r] = g_diff[n_knots - 2, r]


@njit(cache=True, nogil=True, error_model="numpy")
def knot_magnitude(xi, share, counts, share_sums, n_times, size, grad):
    """:meth:`.knot_loss.KnotLoss.magnitude` of the knots ``xi`` (K, m): ``size`` (m,)
    and ``grad`` (K, m) written. Interval k holds ``counts[k]`` samples, at shares
    ``share[k, :counts[k]]`` (summing to ``share_sums[k]``) of the way from its left
    knot to its right. Where both knots have one sign, so has every sample between
    them, and the interval's sums are those of its shares; elsewhere sample by sample."""
    n_knots, m = xi.shape
    zero = xi.dtype.type(0.0)
    for r in range(m):
        total = 0.0
        for k in range(n_knots):
            grad[k, r] = zero
        for k in range(n_knots - 1):
            lo, hi = xi[k, r], xi[k + 1, r]
            if lo * hi > 0:
                sign = xi.dtype.type(_sign(lo))
                total += sign * (counts[k] * float(lo) + share_sums[k] * float(hi - lo))
                on_right = sign * xi.dtype.type(share_sums[k])
                on_left = sign * counts[k] - on_right
            else:
                on_left = on_right = zero
                for s in range(counts[k]):
                    value = lo + share[k, s] * (hi - lo)
                    sign = xi.dtype.type(_sign(value))
                    total += value * sign
                    on_right += sign * share[k, s]
                    on_left += sign - sign * share[k, s]
            grad[k, r] += on_left
            grad[k + 1, r] += on_right
        size[r] = total / n_times
