"""The data rows of the refinement's normal equations, compiled: one call per group.

:meth:`.refine.Problem.equations` runs hundreds of times per discovery on small arrays
(prey-only Lotka-Volterra: about 600 times on 40 segments of 50 samples). Written as
array operations, the residuals and the Jacobian's data rows took a dozen of them,
each a fresh array and most of its cost fixed; here they are one loop.

The arithmetic is that of the array operations, operation by operation: residuals in
noise units masked to the real samples, whitened (:func:`.whiten.whiten`: the previous
sample's share removed, scaled by ``1 / sqrt(1 - a^2)``), times the samples' weights;
the sensitivities alike; each a product or a quotient of two numbers, so the rows are
those of the array version to the bit (a test holds them to it). The square roots are
taken as the array version took them, by torch (:func:`.whiten.scale`): they are not
always the correctly rounded ones that a compiled loop would take.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit

from .whiten import scale


def sample_weights(weights, mask):
    """Data weights (K, M) of a group's padded samples (``mask`` (K, M)) from its
    segments' weights: one per segment (K,) or per sample slot (K, >= M)."""
    w = np.asarray(weights, dtype=np.float64)
    return (w[:, None] if w.ndim == 1 else w[:, :mask.shape[1]]) * mask


def sum_of_squares(values: np.ndarray) -> float:
    """The sum of squares of ``values`` by torch's reduction (its order of summation:
    the misfits every decision compares are those of the torch version, to the bit)."""
    return float(torch.from_numpy(values**2).sum())


def data_rows(vals, sens, observed, mask, sigma, weights, carry, n_states):
    """Residuals (K, M, o) and Jacobian rows (K, M o, free coefficients + states) of a
    group: ``vals`` (K, M, o) the states at the samples, ``sens`` (K, M, o, n +
    free) their sensitivities (by the start, then the free coefficients), ``observed``
    (K, M, o), ``mask`` (K, M) the real samples, ``sigma`` (o,) the noise levels,
    ``weights`` (K, M) the samples' weights, ``carry`` (K, M, o) the AR(1) shares of
    :func:`.whiten.carry_over` or None. The Jacobian's columns are the free
    coefficients', then the start's."""
    whitened = carry is not None
    if whitened:  # each as the array version's torch made it, for its shape
        root, root_sens = scale(carry), scale(carry[..., None])[..., 0]
    else:
        carry = root = root_sens = np.zeros((0, 0, 0))
    return _rows(vals, sens, observed, mask, sigma, weights, carry, root, root_sens,
                 whitened, n_states)


@njit(cache=True, nogil=True, error_model="numpy")  # x / 0: inf or nan, as in torch
def _rows(vals, sens, observed, mask, sigma, weights, carry, root, root_sens, whitened,
          n_states):
    n_seg, n_samples, n_obs = vals.shape
    width = sens.shape[3]
    resid = np.empty((n_seg, n_samples, n_obs))
    jac = np.empty((n_seg, n_samples * n_obs, width))
    before = np.zeros(width)  # the previous sample's unwhitened sensitivities
    for k in range(n_seg):
        for c in range(n_obs):
            last = 0.0  # the previous sample's unwhitened residual
            for j in range(width):
                before[j] = 0.0
            for m in range(n_samples):
                real = 1.0 if mask[k, m] else 0.0
                w = weights[k, m]
                r = (vals[k, m, c] - observed[k, m, c]) / sigma[c] * real
                if whitened:
                    a, root_s = carry[k, m, c], root_sens[k, m, c]
                    resid[k, m, c] = (r - a * last) / root[k, m, c] * w
                else:
                    resid[k, m, c] = r * w
                last = r
                row = m * n_obs + c
                for j in range(width):
                    s = sens[k, m, c, j] / sigma[c] * real
                    col = j - n_states if j >= n_states else width - n_states + j
                    if whitened:
                        jac[k, row, col] = (s - a * before[j]) / root_s * w
                    else:
                        jac[k, row, col] = s * w
                    before[j] = s
    return resid, jac
