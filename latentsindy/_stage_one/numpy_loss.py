"""The loss of :mod:`.loss` on a coefficient series in numpy, and its gradient written
out: the numpy step's loss.

The misfit, the magnitude and the roughness are evaluated here (on the samples) or by
:class:`.knot_loss.KnotLoss` (on the decoder's knots), each with its gradient; their
assembly, weights and shares are :mod:`.loss`'s (:func:`.loss.penalties`,
:func:`.loss.term_weights`, ...), whose derivatives are written here. The arithmetic
runs in the data's precision (float32 in training; float64 in the tests that hold the
three paths of the loss to each other).
"""

from __future__ import annotations

import numpy as np

from .loss import (
    BEND_SHARE,
    TERMS,
    TV_SHARE,
    kl_in_mse_units,
    penalties,
    roughness_scale,
    sparsity_gradient,
    term_weights,
)


def time_mean(a):
    """Mean over the first axis (time), accumulated in float64, as one matrix-vector
    product (numpy's own reduction over the rows of a (T, few) array loops over T short
    rows). The precision matters: a constant's gradient is such a sum, of terms that
    cancel near the optimum, and Adam scales whatever is left, rounding included, to a
    full step (float32 accumulation cost a structure on a driven oscillator at 10%
    noise that torch's cascade sums find)."""
    ones = np.full(a.shape[0], 1.0 / a.shape[0])
    return (ones @ a.reshape(a.shape[0], -1).astype(np.float64)).reshape(
        a.shape[1:]).astype(a.dtype)


class NumpyLoss:
    """The loss's terms on a coefficient series and their gradient by it.

    Parameters
    ----------
    theta : (B, T, F) array
    xdot, weights : (B, T, n) arrays
    noise_var, threshold : float
    free : (n,) array
        1 on the rows the sparsity acts on, else 0.
    spacing : (T - 1,) array or None
        :func:`.loss.relative_spacing` of the sample times (None: equal steps).
    on_knots : KnotLoss or None
        Given: the series passed are the decoder's knots, and ``on_knots`` evaluates
        the misfit, magnitude and roughness (``spacing`` is then None).
    """

    def __init__(self, theta, xdot, weights, noise_var, threshold, free, spacing=None,
                 on_knots=None):
        self.theta, self.xdot, self.weights = theta, xdot, weights
        self.noise_var, self.threshold = float(noise_var), float(threshold)
        self.free = free.astype(theta.dtype)
        self.spacing = None if spacing is None else spacing[:, None, None]
        self.on_knots = on_knots
        self.n_times = theta.shape[1]

    def __call__(self, xi, support, kl, l1_weight, rough_weight, kl_weight, rough_scaled):
        """Terms (:data:`.loss.TERMS`, floats) of the coefficients ``xi`` ((T or K, n, F):
        masked by ``support``, float (n, F)) and the generator's KL divergence ``kl``;
        the gradient of :func:`.loss.total_loss` with these weights by ``xi``, and the
        loss's derivative by ``kl``."""
        if self.on_knots is not None:  # xi (n_knots, n, F): the knots' values
            mse, grad_xi = self.on_knots.misfit(xi)
            size, sign = self.on_knots.magnitude(xi)
            size = size * support
            rough_raw, grad_rough = self.on_knots.roughness(xi)
        else:  # xi (T, n, F): the samples'
            pred = np.einsum("btf,tnf->btn", self.theta, xi)
            resid = pred - self.xdot
            wr = self.weights * resid
            mse = float(np.mean(wr * resid))
            grad_pred = wr * xi.dtype.type(2.0 / resid.size)
            grad_xi = np.einsum("btn,btf->tnf", grad_pred, self.theta)
            sign = np.sign(xi)
            size = time_mean(np.abs(xi)) * support
            rough_raw, grad_rough = self._roughness(xi)
        n_times = self.n_times
        parts, n_active, mean_abs = penalties(size, rough_raw, support, self.free,
                                              self.threshold, self.noise_var, n_times,
                                              self.xdot.shape[-1])
        kl_scale = kl_in_mse_units(1.0, self.noise_var, self.xdot.size)
        values = {"mse": mse, "kl": kl_scale * kl, **parts}
        weights = term_weights(l1_weight, rough_weight, kl_weight, rough_scaled,
                               parts["rough_bayes"])
        c_rough = weights["rough"] * roughness_scale(n_active, mean_abs, self.threshold)
        grad_size = sparsity_gradient(size, self.threshold, self.free, weights["l1"]) * support
        grad_xi += sign * (grad_size / n_times).astype(xi.dtype)
        grad_xi += grad_rough * (xi.dtype.type(c_rough) * support)
        return {k: values[k] for k in TERMS}, grad_xi, weights["kl"] * kl_scale

    def _roughness(self, xi):
        """:func:`.loss.roughness` per term of the samples ``xi``, and its gradient."""
        n_times, real = xi.shape[0], xi.dtype.type
        if n_times < 3:
            return np.zeros(xi.shape[1:], xi.dtype), np.zeros_like(xi)
        first = xi[1:] - xi[:-1]
        grad = np.zeros_like(xi)
        if self.spacing is None:
            curve = xi[2:] - 2 * xi[1:-1] + xi[:-2]
            g2 = np.sign(curve) * real(BEND_SHARE / (n_times - 2))
            grad[2:] += g2
            grad[1:-1] -= 2 * g2
            grad[:-2] += g2
            second = np.abs(curve)
        else:
            h = self.spacing
            slope = first / h
            change = slope[1:] - slope[:-1]
            width = h[1:] + h[:-1]
            second = np.abs(2 * change / width) * (width / 2)
            g_slope = np.zeros_like(slope)
            g2 = np.sign(change) * real(BEND_SHARE / (n_times - 2))
            g_slope[1:] += g2
            g_slope[:-1] -= g2
            g_first = g_slope / h
            grad[1:] += g_first
            grad[:-1] -= g_first
        g1 = np.sign(first) * real(TV_SHARE / (n_times - 1))
        grad[1:] += g1
        grad[:-1] -= g1
        value = BEND_SHARE * time_mean(second) + TV_SHARE * time_mean(np.abs(first))
        return value, grad
