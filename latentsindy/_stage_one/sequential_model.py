"""The sequential coefficient model: gated coefficients read chunk by chunk, and the
loss of one window (misfit, KL, roughness) that the windowed training minimises."""

from __future__ import annotations

import math

import torch
from torch import nn

from ..generators.hypersindy import chunk_centres, interpolate_at, interpolate_chunks
from .coefficient_model import CoefficientModel, least_squares_constants
from .loss import roughness

# hard-concrete gate constants (Louizos et al. 2018)
_BETA, _GAMMA, _ZETA = 2.0 / 3.0, -0.1, 1.1
_LOG_ALPHA0 = 5.0  # gates (on terms and on their variation) start open: P(gate < 1) = 3%


class SequentialCoefficientModel(CoefficientModel):
    """Xi = support * gate * (constants + time_varying * generator), chunk by chunk."""

    def __init__(self, generator, constants, support, time_varying):
        super().__init__(generator, constants, support, time_varying)
        self.log_alpha = nn.Parameter(torch.full_like(constants, _LOG_ALPHA0))
        # gates on each term's time variation: a term whose variation is not needed
        # closes its gate and is fitted as a constant
        self.log_alpha_var = nn.Parameter(torch.full_like(constants, _LOG_ALPHA0))
        self.track_mean = None  # online mode: coefficients read off while training
        self.track_std = None
        self.last_size = None

    def gates(self, stochastic: bool, log_alpha=None) -> torch.Tensor:
        """Hard-concrete gates in [0, 1]: sampled in training, their median otherwise."""
        log_alpha = self.log_alpha if log_alpha is None else log_alpha
        if stochastic:
            u = torch.rand_like(log_alpha).clamp(1e-6, 1 - 1e-6)
            s = torch.sigmoid((torch.log(u) - torch.log1p(-u) + log_alpha) / _BETA)
        else:
            s = torch.sigmoid(log_alpha)
        return (s * (_ZETA - _GAMMA) + _GAMMA).clamp(0.0, 1.0)

    def expected_l0(self, log_alpha=None) -> torch.Tensor:
        """Probability that each gate is non-zero, (n_states, n_features)."""
        log_alpha = self.log_alpha if log_alpha is None else log_alpha
        return torch.sigmoid(log_alpha - _BETA * math.log(-_GAMMA / _ZETA))

    def window(self, inputs, n_samples, state, stochastic=False, start=0):
        """Chunk coefficients (S, C, n, F) of one window, its KL and the new state."""
        series, kl, state = self.generator.window(inputs, n_samples, state, start)
        n_states, n_features = self.constants.shape
        series = series.reshape(series.shape[0], series.shape[1], n_states, n_features)
        varying = self.time_varying * self.gates(stochastic, self.log_alpha_var)
        ungated = self.support * (self.effective_constants() + varying * series)
        self.last_size = ungated.abs().mean(dim=(0, 1)) * self.gates(False).detach()
        return ungated * self.gates(stochastic), kl, state

    def chunk_series(self, inputs, n_samples, window):
        """Chunk coefficients (S, C, n, F) of the whole series, read window by window."""
        if self.track_mean is not None:
            mean = self.track_mean[None]
            if n_samples == 0:
                return mean, torch.zeros((), device=mean.device)
            eps = torch.randn((n_samples, *self.track_mean.shape), device=mean.device)
            return mean + eps * self.track_std[None], torch.zeros((), device=mean.device)
        state, parts, kl = None, [], 0.0
        for start in range(0, inputs.shape[-1], window):
            xi, kl_w, state = self.window(inputs[..., start:start + window], n_samples, state,
                                          start=start)
            parts.append(xi)
            kl = kl + kl_w
        return torch.cat(parts, dim=1), kl

    @torch.no_grad()
    def mean_blocks(self, inputs, block: int = 100_000):
        """Yield (start, stop, Xi): mean per-step coefficients, ``block`` steps at a time."""
        chunk, n_times = self.generator.chunk, inputs.shape[-1]
        positions = self.generator.positions
        xi, _ = self.chunk_series(inputs, 0, self.generator.window_len)
        values = xi.flatten(2)
        centres = chunk_centres(0, n_times, chunk, values.dtype, values.device, positions)
        for lo in range(0, n_times, block):
            hi = min(lo + block, n_times)
            steps = _steps(lo, hi, positions, values)
            yield lo, hi, interpolate_at(values, centres, steps)[0].reshape(hi - lo,
                                                                            *xi.shape[2:])

    @torch.no_grad()
    def restore_constant(self, i: int, j: int) -> None:
        super().restore_constant(i, j)
        self.log_alpha[i, j] = _LOG_ALPHA0  # its gate reopens

    @torch.no_grad()
    def freeze_constant(self, i: int, j: int, value: float) -> None:
        gate = float(self.gates(False)[i, j])  # the read-out multiplies by the gate
        super().freeze_constant(i, j, value / gate if gate > 0 else value)

    @torch.no_grad()
    def pin_constant(self, i: int, j: int, value: float) -> None:
        self.log_alpha[i, j] = max(float(self.log_alpha[i, j]), _LOG_ALPHA0)  # gate open
        gate = float(self.gates(False)[i, j])
        super().pin_constant(i, j, value / gate if gate > 0 else value)

    @torch.no_grad()
    def free_variation(self, i: int, j: int) -> None:
        """Let term ``j`` of equation ``i`` vary (its variation gate reopens)."""
        self.time_varying[i, j] = 1.0
        self.log_alpha_var[i, j] = _LOG_ALPHA0

    def forward(self, inputs, n_samples: int):
        """Per-step coefficients (S, T, n, F) and KL, as :class:`CoefficientModel`."""
        chunk, window = self.generator.chunk, self.generator.window_len
        xi, kl = self.chunk_series(inputs, n_samples, window)
        shape = xi.shape
        per_step = interpolate_chunks(xi.flatten(2), inputs.shape[-1], chunk,
                                      self.generator.positions)
        return per_step.reshape(shape[0], -1, *shape[2:]), kl


def windowed_constants(theta, xdot, support, window):
    """Initial constants: the average of least-squares fits in each window.

    A single constant fit of a time-varying system borrows spurious terms to mimic the
    variation (on Lorenz with a drifting sigma it uses x z and y z); window by window
    the variation is small, those terms are not needed, and their average is near zero.
    Accumulates one window at a time, so memory does not depend on the series length.
    """
    n_states, n_features = support.shape
    fits, weights = [], []
    for start in range(0, theta.shape[1], window):
        a = theta[:, start:start + window].reshape(-1, n_features)
        b = xdot[:, start:start + window].reshape(-1, n_states)
        if a.shape[0] < 2 * n_features:  # too short for a fit of its own
            continue
        fits.append(least_squares_constants(a[None], b[None], support))
        weights.append(float(a.shape[0]))
    if not fits:
        return least_squares_constants(theta, xdot, support)
    w = torch.tensor(weights, dtype=theta.dtype, device=theta.device)
    return (torch.stack(fits) * w[:, None, None]).sum(0) / w.sum()


def window_loss(model, theta, xdot, weights, inputs, noise_var, state, previous,
                 stochastic, start, stop, floor):
    """Loss terms of the window starting at ``start``; returns (terms, chunk
    coefficients, new state).

    The misfit covers the steps from the previous window's last chunk centre to this
    window's last chunk centre, interpolating from the previous window's last chunk, so
    training sees exactly the coefficients that the whole-series read-out interpolates.
    """
    chunk, n_times = model.generator.chunk, theta.shape[1]
    positions = model.generator.positions
    xi_c, kl, state = model.window(inputs[..., start:stop], 1, state, stochastic=stochastic,
                                   start=start)
    centres = chunk_centres(start, stop, chunk, theta.dtype, theta.device, positions)
    values = xi_c.flatten(2)
    if previous is not None:
        before = chunk_centres(start - chunk, start, chunk, theta.dtype, theta.device,
                               positions)
        centres = torch.cat([before, centres])
        values = torch.cat([previous.flatten(2), values], dim=1)
    # the steps from the previous chunk centre (exclusive) to the last one (inclusive)
    lo = _first_after(centres[0], positions) if previous is not None else start
    hi = _first_after(centres[-1], positions) if stop < n_times else n_times
    steps = _steps(lo, hi, positions, theta)
    xi = interpolate_at(values, centres, steps).reshape(xi_c.shape[0], hi - lo,
                                                        *xi_c.shape[2:])
    xdot_w = xdot[:, lo:hi]
    pred = torch.einsum("btf,stnf->sbtn", theta[:, lo:hi], xi)
    mse = torch.mean(weights[None, :, lo:hi] * (pred - xdot_w[None]) ** 2)
    kl = 2.0 * noise_var * kl / xdot_w.numel()
    active = model.support.to(xi.dtype)
    n_active = active.sum().clamp_min(1.0)
    track = xi_c if previous is None else torch.cat([previous, xi_c], dim=1)
    # slope changes of the chunk track, per time step of the window
    spacing = None if positions is None else torch.diff(centres)
    per_term = roughness(track, spacing) * (track.shape[1] - 2) / max(hi - lo, 1)
    size = model.last_size  # mean |Xi| in this window, with the gates' expected values
    scale = n_active * torch.clamp((size * active).sum() / n_active, min=floor).detach()
    rough = (per_term * active).sum() / scale
    shared = shared_variation(model)
    rough_shared = (per_term * shared).sum() / scale
    return {"mse": mse, "kl": kl, "rough": rough, "rough_shared": rough_shared,
            "rough_lone": rough - rough_shared, "size": size}, xi_c, state


def _steps(lo, hi, positions, like):
    """Time coordinates of steps [lo, hi): the step indices, or their positions."""
    if positions is None:
        return torch.arange(lo, hi, dtype=like.dtype, device=like.device)
    return positions[lo:hi].to(like.dtype)


def _first_after(centre, positions):
    """Index of the first step after time ``centre`` (in steps, or in positions)."""
    if positions is None:
        return int(math.floor(float(centre))) + 1
    return int(torch.searchsorted(positions, centre, right=True))


def shared_variation(model) -> torch.Tensor:
    """Mask of the varying terms whose equation has another varying term.

    One varying term in an equation is identified pointwise (``xdot = h(t) x`` gives
    h = xdot / x), and the random-walk prior of the latents is its smoothness prior.
    Two or more can trade off along the trajectory (``a(t) x + b(t) y`` fits any
    residual with state-dependent wiggles); only a smoothness penalty on each resolves
    that, so the refit smooths these more (``refit_smoothness`` against
    ``lone_smoothness``).
    """
    varying = model.time_varying * model.support
    return varying * (varying.sum(dim=1, keepdim=True) >= 2)
