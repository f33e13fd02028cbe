"""A pysindy differentiation method applied to recordings: their derivatives, the noise
each derivative carries, and the samples' weights in stage one's likelihood."""

from __future__ import annotations

import copy

import numpy as np

from .derivatives import AdaptiveSavitzkyGolay, default_differentiation, noise_level, state_noise
from .timing import timed


def derivative_noise_std(method, x, t, x_dot, sigma=None):
    """Standard deviation of the noise that ``method`` passes into each derivative.

    The states' noise level ``sigma`` comes from high-order differences (on the actual
    times; estimated from ``x`` when not given); the method's gain from its own
    coefficients (the default: on AR(1) noise where the noise reads as correlated) or,
    for any other method, from its response to a small white-noise perturbation (exact
    for linear methods on white noise).
    """
    if sigma is None:
        sigma = noise_level(x, t if np.ndim(t) else None)
    gain = getattr(method, "noise_gain_", None)
    if gain is None or len(gain) != x.shape[1]:
        eps = 1e-3 * np.maximum(x.std(axis=0), 1e-12)
        noise = np.random.default_rng(0).standard_normal(x.shape)
        response = (np.asarray(method(x + eps * noise, t)) - x_dot) / eps
        gain = np.var(response[5:-5], axis=0)
    return sigma * np.sqrt(gain)


@timed("differentiation")
def differentiate(method, trajectories, times):
    """Apply a pysindy differentiation method to each trajectory; reject NaN edges.

    Returns the derivatives, the derivative noise std per state (the states' noise
    level pooled over the trajectories, each trajectory's gain weighted by its
    samples), and per-sample likelihood weights (the inverse relative noise variance;
    zero within half a window of either end, where a smoothing differentiator
    extrapolates).
    """
    method = method if method is not None else default_differentiation()
    if not callable(method):
        raise TypeError(
            "differentiation_method must be a pysindy differentiation object such as "
            f"ps.SmoothedFiniteDifference(); got {type(method).__name__}."
        )
    out, noise, weights = [], [], []
    grids = [t if np.ndim(t) else None for t in times]
    if not isinstance(method, AdaptiveSavitzkyGolay):
        sigma = noise_level(list(trajectories), grids)
    elif method.noise_std is not None:
        sigma = np.asarray(method._sigmas(trajectories[0].shape[1]))
    else:  # one instrument: its noise level (white or AR(1)) from all samples
        sigma, phi = state_noise(list(trajectories), grids)
        method = copy.copy(method)
        method.noise_std = sigma
        if method.noise_correlation is None:
            method.noise_correlation = phi
    for x, t in zip(trajectories, times, strict=True):
        d = np.asarray(method(x, t), dtype=float)
        if d.shape != x.shape or not np.all(np.isfinite(d)):
            raise ValueError(
                f"{type(method).__name__} returned derivatives of shape {d.shape} with "
                f"{int(np.sum(~np.isfinite(d)))} non-finite values for data of shape {x.shape}; "
                "use a method that fills the edges (e.g. FiniteDifference(drop_endpoints=False))."
            )
        noise.append(derivative_noise_std(method, x, t, d, sigma))
        profile = getattr(method, "noise_profile_", None)
        weights.append(1.0 / profile if profile is not None and profile.shape == x.shape
                       else np.ones_like(x))
        for j, w in enumerate(getattr(method, "windows_", [])[:x.shape[1]]):
            # within half a window of either end the derivative is extrapolated: it is
            # noisier and biased, so it does not enter the likelihood at all
            weights[-1][: w // 2, j] = 0.0
            weights[-1][x.shape[0] - w // 2:, j] = 0.0
        out.append(d)
    return out, np.average(noise, axis=0, weights=[len(x) for x in trajectories]), weights
