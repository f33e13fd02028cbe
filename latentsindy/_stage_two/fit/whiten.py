"""Residuals of AR(1) measurement noise made white (generalised least squares).

With AR(1) noise of correlation ``phi`` between samples a step ``dt`` apart, the
residual ``e_i`` of a right system, less ``a_i e_(i-1)`` with ``a_i = phi^(gap/dt)``
(the gap between the two samples), scaled by ``1 / sqrt(1 - a_i^2)``, is white with
the noise's variance; a segment's first residual stays as it is. The refinement's
likelihood, term selection and held-out scores then count each sample's new
information once (correlation 0.9 makes 2000 samples worth about 105 independent ones,
and white-noise statistics would count them as 2000).
"""

from __future__ import annotations

import numpy as np
import torch


def carry_over(groups, phi, dt):
    """Per group, ``a`` (K, M, n_observed): the share of the previous residual in each
    sample's (0 for a segment's first sample, for padding, and for white states)."""
    phi = np.asarray(phi, float)
    if not np.any(phi > 0):
        return None
    out = []
    for g in groups:
        pos = g.positions.cpu().numpy()
        mask = g.mask.cpu().numpy()
        gap = np.zeros_like(pos)
        gap[:, 1:] = (pos[:, 1:] - pos[:, :-1]) / dt
        real = np.zeros_like(mask)
        real[:, 1:] = mask[:, 1:] & mask[:, :-1]
        with np.errstate(divide="ignore"):
            a = np.where(real[..., None], phi[None, None, :] ** gap[..., None], 0.0)
        out.append(torch.as_tensor(a, dtype=torch.float64))
    return out


def whiten(values, a):
    """``values`` (K, M, n_observed, ...) whitened along the samples (``a`` from
    :func:`carry_over`, or its numpy array; None: unchanged), tensors or numpy arrays
    (the same arithmetic)."""
    if a is None:
        return values
    while a.ndim < values.ndim:
        a = a[..., None]
    xp = np if isinstance(values, np.ndarray) else torch
    previous = xp.zeros_like(values)
    previous[:, 1:] = values[:, :-1]
    return (values - a * previous) / (scale(a) if xp is np else torch.sqrt(1.0 - a**2))


def scale(a: np.ndarray) -> np.ndarray:
    """``sqrt(1 - a^2)`` for the numpy array ``a``, as torch computes it: its vectorised
    square root is within an ulp, not always the correctly rounded one (1.4% of
    float64 values differ from numpy's), and the misfits in numpy are those that the
    held-out scores make in torch, to the bit."""
    return torch.sqrt(1.0 - torch.from_numpy(np.asarray(a)) ** 2).numpy()
