"""Window-by-window training of sequential generators (dynamic HyperSINDy).

The series is read in time order in windows; the hypernetwork's state is carried from
one window to the next and detached (truncated backpropagation through time), so
memory is set by the window, not by the series length (the per-chunk latent offsets,
25 numbers per 10 steps, are the only per-sample parameters; a step updates its
window's rows only). The loss is the one of
:mod:`latentsindy._training` (derivative misfit, KL in ELBO units, sparsity, normalised
total variation) with the paper's HyperSINDy choices: relaxed-L0 (hard-concrete)
gates, a KL weight warmed up from ``kl_start``, AdamW with amsgrad and an exponential
learning-rate decay.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn
from tqdm.auto import tqdm

from ._selection import freeze_constant_terms, restore_absorbed_terms, restore_terms
from ._training import (
    CoefficientModel,
    check_nonnegative_fields,
    least_squares_constants,
    roughness,
)
from .generators.hypersindy import (
    chunk_centres,
    detach_state,
    interpolate_at,
    interpolate_chunks,
)

MODES = ("alternate", "joint", "online")
# hard-concrete gate constants (Louizos et al. 2018)
_BETA, _GAMMA, _ZETA = 2.0 / 3.0, -0.1, 1.1
_LOG_ALPHA0 = 5.0  # gates (on terms and on their variation) start open: P(gate < 1) = 3%
_HYPERNETWORK = ("generator.lstm", "generator.mlp", "generator.to_alpha")  # parameter names
_GATE_LR = 10.0  # gates learn ten times faster than the networks
_CODE_LR = 30.0  # per-chunk offsets: one update per epoch each, so large steps


@dataclass(frozen=True)
class SequentialTrainingOptions:
    """How a sequential generator (``generator="hypersindy"``) is trained.

    Weights act on normalised quantities, as in :class:`TrainingOptions`.

    Attributes
    ----------
    mode : {"joint", "alternate", "online"}
        ``"joint"`` (default): every part is trained at every step. ``"alternate"``
        (the paper's mode for continuously varying coefficients): the hypernetwork and
        the main module (encoder, decoder, basis tensors, offsets, constants, gates)
        take turns, one epoch each; measured slower to converge and, on a single
        window, not converging. ``"online"``: the support phase as in ``"joint"``,
        then one pass in time order in which the main module adapts to each window
        for ``online_steps`` steps and the coefficients are read off as it goes (the
        paper's mode for switching systems; the hypernetwork is not used). Switch
        points are then read off the track: ``coefficients().switch_times()``.
    window : int
        Time steps per optimiser step (truncated backpropagation length).
    support_steps, refit_steps : int
        Optimiser steps of phase one (support) and phase two (refit), each rounded
        up to whole passes over the series (epochs), at least ``min_epochs``.
    min_epochs : int
        Fewest passes over the series per phase (long series need few).
    learning_rate, weight_decay, lr_decay : float
        AdamW (amsgrad) step size and weight decay; the step size is multiplied by
        ``lr_decay`` after every optimiser step.
    threshold : float
        Final pruning threshold on a term's mean |coefficient| over time (a share of
        its equation's RMS derivative), reached by a linear rise after the warm-up.
    warmup, ramp : float
        Fractions of phase one without pruning (with one latent per window, so the
        coefficients are constant within a window), and at which the threshold is full.
    sparsity : float
        Weight of the relaxed-L0 penalty (expected number of active terms per
        equation) in phase one.
    l1 : float
        Weight of the reweighted-L1 (log) penalty on each term's mean |Xi|, per
        equation, in phase one (as ``TrainingOptions.sparsity``).
    variation_sparsity : float
        Cost of letting a term vary in time (relaxed L0 on its variation gate, per
        equation), plus twice the derivative noise variance: a term varies only where
        that explains more than noise. Terms whose variation gate closes in phase
        one are refitted as constants.
    kl_start, kl_weight : float
        The KL weight rises geometrically from ``kl_start`` to ``kl_weight`` over
        phase one (the paper's KL warm-up) and stays there.
    smoothness, refit_smoothness : float
        Weights of the normalised total variation, as in :class:`TrainingOptions`; in
        the refit, ``refit_smoothness`` acts on terms that vary together with another
        term of their equation: only a smoothness penalty keeps such terms from
        trading off with state-dependent wiggles (Lorenz's sigma(t) in ``-sigma x +
        sigma y``, T=10,000, 1% noise, three seeds: R^2 0.97, 0.94, 0.76 with 2,
        0.997, 0.996, 0.996 with 10).
    lone_smoothness : float
        Refit weight of the total variation on a term that is its equation's only
        varying term: identified pointwise by the data, it needs smoothing only against
        noise, and a strong TV prior (total variation about one coefficient size)
        flattens it where the data say little; an oscillating hidden state varies far
        more than that (prey-only LV at 1% noise, five seed pairs: max error 5.7% with
        2.0, 2.8% with 0.5; without it, 5% noise loses the hidden terms).
    grad_clip : float
        Maximum gradient norm.
    online_steps : int
        Optimiser steps per window in ``mode="online"``.
    """

    mode: str = "joint"
    window: int = 1000
    support_steps: int = 800
    refit_steps: int = 700
    min_epochs: int = 2
    learning_rate: float = 3e-3
    weight_decay: float = 1e-5
    lr_decay: float = 0.999
    threshold: float = 0.05
    warmup: float = 0.25
    ramp: float = 0.75
    sparsity: float = 1e-3
    l1: float = 0.1
    variation_sparsity: float = 1e-3
    kl_start: float = 0.01
    kl_weight: float = 1.0
    smoothness: float = 0.3
    refit_smoothness: float = 10.0
    lone_smoothness: float = 0.5
    grad_clip: float = 1.0
    online_steps: int = 20

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"SequentialTrainingOptions.mode must be one of {MODES}; "
                             f"got {self.mode!r}.")
        check_nonnegative_fields(self, skip=("mode",))
        for name in ("window", "min_epochs", "online_steps"):
            if getattr(self, name) < 1:
                raise ValueError(f"SequentialTrainingOptions.{name} must be >= 1; "
                                 f"got {getattr(self, name)}")
        if not 0 <= self.warmup < self.ramp <= 1:
            raise ValueError("SequentialTrainingOptions needs 0 <= warmup < ramp <= 1; got "
                             f"warmup={self.warmup}, ramp={self.ramp}")
        if self.learning_rate <= 0 or not 0 < self.lr_decay <= 1:
            raise ValueError("SequentialTrainingOptions needs learning_rate > 0 and "
                             f"0 < lr_decay <= 1; got {self.learning_rate}, {self.lr_decay}")
        if not 0 < self.kl_start <= max(self.kl_weight, self.kl_start):
            raise ValueError(f"SequentialTrainingOptions.kl_start must be > 0; "
                             f"got {self.kl_start}")


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
        ungated = self.support * (self.constants + varying * series)
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
        xi, _ = self.chunk_series(inputs, 0, self.generator.window_len)
        values = xi.flatten(2)
        centres = chunk_centres(0, n_times, chunk, values.dtype, values.device)
        for lo in range(0, n_times, block):
            hi = min(lo + block, n_times)
            steps = torch.arange(lo, hi, dtype=values.dtype, device=values.device)
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

    def forward(self, inputs, n_samples: int):
        """Per-step coefficients (S, T, n, F) and KL, as :class:`CoefficientModel`."""
        chunk, window = self.generator.chunk, self.generator.window_len
        xi, kl = self.chunk_series(inputs, n_samples, window)
        shape = xi.shape
        per_step = interpolate_chunks(xi.flatten(2), inputs.shape[-1], chunk)
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


def _window_loss(model, theta, xdot, weights, inputs, noise_var, state, previous,
                 stochastic, start, stop, floor):
    """Loss terms of the window starting at ``start``; returns (terms, chunk
    coefficients, new state).

    The misfit covers the steps from the previous window's last chunk centre to this
    window's last chunk centre, interpolating from the previous window's last chunk, so
    training sees exactly the coefficients that the whole-series read-out interpolates.
    """
    chunk, n_times = model.generator.chunk, theta.shape[1]
    xi_c, kl, state = model.window(inputs[..., start:stop], 1, state, stochastic=stochastic,
                                   start=start)
    centres = chunk_centres(start, stop, chunk, theta.dtype, theta.device)
    values = xi_c.flatten(2)
    if previous is not None:
        centres = torch.cat([centres.new_tensor([start - (chunk + 1) / 2]), centres])
        values = torch.cat([previous.flatten(2), values], dim=1)
    lo = int(math.floor(float(centres[0]))) + 1 if previous is not None else start
    hi = int(math.floor(float(centres[-1]))) + 1 if stop < n_times else n_times
    steps = torch.arange(lo, hi, dtype=theta.dtype, device=theta.device)
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
    per_term = roughness(track) * (track.shape[1] - 2) / max(hi - lo, 1)
    size = model.last_size  # mean |Xi| in this window, with the gates' expected values
    scale = n_active * torch.clamp((size * active).sum() / n_active, min=floor).detach()
    rough = (per_term * active).sum() / scale
    shared = shared_variation(model)
    rough_shared = (per_term * shared).sum() / scale
    return {"mse": mse, "kl": kl, "rough": rough, "rough_shared": rough_shared,
            "rough_lone": rough - rough_shared, "size": size}, xi_c, state


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


def _refit_roughness(terms, options):
    return (options.refit_smoothness * terms["rough_shared"]
            + options.lone_smoothness * terms["rough_lone"])


def _epochs(steps, per_epoch, minimum):
    return max(minimum, math.ceil(steps / per_epoch)) if steps else 0


def train_sequential(model, theta, xdot, weights, inputs, noise_var, free_rows,
                     options: SequentialTrainingOptions, verbose: bool):
    """Two-phase windowed training in place; returns the loss history (one dict per step)."""
    chunk = model.generator.chunk
    n_times = theta.shape[1]
    window = max(chunk, options.window - options.window % chunk)
    model.generator.window_len = window
    starts = list(range(0, n_times, window))
    hyper = [p for name, p in model.named_parameters() if name.startswith(_HYPERNETWORK)]
    gates = [model.log_alpha, model.log_alpha_var]
    codes = [model.generator.codes.weight] if model.generator.codes is not None else []
    skip = {id(p) for p in hyper + gates + codes}
    main = [p for p in model.parameters() if id(p) not in skip]
    lr = options.learning_rate
    make = lambda groups: torch.optim.AdamW(groups, lr=lr,  # noqa: E731
                                            weight_decay=options.weight_decay, amsgrad=True)
    optimisers = {"main": make([{"params": main},
                                {"params": gates, "lr": lr * _GATE_LR, "weight_decay": 0.0}]),
                  "hyper": make([{"params": hyper}])}
    if codes:  # sparse rows: a step updates only its window's offsets
        optimisers["codes"] = torch.optim.SparseAdam(codes, lr=lr * _CODE_LR)
    var_cost = options.variation_sparsity + 2.0 * noise_var
    shifted = n_times > window  # window grids shift every epoch (see below)
    per_epoch = len(starts) + int(shifted)
    epochs = (_epochs(options.support_steps, per_epoch, options.min_epochs),
              _epochs(options.refit_steps, per_epoch, options.min_epochs))
    total_steps = sum(epochs) * per_epoch
    free = free_rows.to(theta.dtype)[:, None]
    bayes = min(1.0, max(0.01, noise_var * n_times * float(model.support.sum())
                         / xdot.shape[-1]))
    n_states = float(xdot.shape[-1])
    history = []
    bar = tqdm(total=total_steps, disable=not verbose, desc="dynamic HyperSINDy", leave=False)
    for phase, n_epochs in ((1, epochs[0]), (2, epochs[1])):
        if phase == 2:
            with torch.no_grad():  # closed variation gates: fitted as constants from now on
                model.time_varying *= (model.gates(False, model.log_alpha_var) > 0).to(
                    model.time_varying.dtype)
            model.log_alpha.requires_grad_(False)
            model.log_alpha_var.requires_grad_(False)
            freeze_constant_terms(model, theta, xdot, weights, inputs, var_cost, free_rows)
            model.restored = restore_terms(model, theta, xdot, weights, inputs,
                                           options.threshold, free_rows)
            model.restored += restore_absorbed_terms(model, theta, xdot, weights, inputs,
                                                     options.threshold, free_rows)
            if options.mode == "online":
                history += _online_pass(model, theta, xdot, weights, inputs, noise_var, starts,
                                        window, options, bayes, bar)
                break
        for epoch in range(n_epochs):
            progress = epoch / max(n_epochs, 1)
            warming = phase == 1 and progress < options.warmup
            if phase == 1:
                rise = min(1.0, progress / options.ramp)
                kl_w = options.kl_start * (options.kl_weight / options.kl_start) ** rise
            else:
                kl_w = options.kl_weight
            if options.mode == "alternate" and n_epochs > 1:
                active_groups = ("hyper",) if (epoch % 2 == 0) else ("main", "codes")
            else:
                active_groups = ("main", "hyper", "codes")
            active_groups = tuple(g for g in active_groups if g in optimisers)
            # a fresh window grid every epoch (shifted by whole chunks): no chunk sits at
            # the end of a window, where it is fitted from one side only, every epoch
            offset = chunk * int(torch.randint(0, window // chunk, ())) if shifted else 0
            bounds = ([0] if offset else []) + list(range(offset, n_times, window)) + [n_times]
            state, previous = None, None
            size_sum, n_chunks = torch.zeros_like(model.constants), 0
            for start, stop in zip(bounds[:-1], bounds[1:], strict=True):
                terms, xi_c, state = _window_loss(
                    model, theta, xdot, weights, inputs, noise_var, state, previous,
                    stochastic=phase == 1, start=start, stop=stop, floor=options.threshold)
                state = detach_state(state)
                previous = xi_c[:, -1:].detach()
                size_sum += terms["size"].detach() * xi_c.shape[1]
                n_chunks += xi_c.shape[1]
                if phase == 1:
                    l0 = (model.expected_l0() * model.support * free).sum() / n_states
                    th = options.threshold
                    l1 = (th * torch.log1p(terms["size"] / th) * free).sum() / n_states
                    l0_var = (model.expected_l0(model.log_alpha_var) * model.time_varying
                              * model.support * free).sum() / n_states
                    reg = options.sparsity * l0 + options.l1 * l1 + var_cost * l0_var \
                        + options.smoothness * terms["rough"]
                else:
                    l0 = torch.zeros(())
                    reg = bayes * _refit_roughness(terms, options)
                loss = terms["mse"] + kl_w * terms["kl"] + reg
                for name in active_groups:
                    optimisers[name].zero_grad(set_to_none=True)
                loss.backward()
                params = [p for name in active_groups if name != "codes"
                          for g in optimisers[name].param_groups for p in g["params"]]
                nn.utils.clip_grad_norm_(params, options.grad_clip)
                for name in active_groups:
                    optimisers[name].step()
                for opt in optimisers.values():
                    for g in opt.param_groups:
                        g["lr"] *= options.lr_decay
                for name in optimisers:
                    if name not in active_groups:
                        optimisers[name].zero_grad(set_to_none=True)
                history.append({"phase": phase, "epoch": epoch, "loss": float(loss.detach()),
                                "mse": float(terms["mse"].detach()),
                                "kl": float(terms["kl"].detach()),
                                "rough": float(terms["rough"].detach()),
                                "l0": float(l0.detach()),
                                "kl_weight": kl_w, "trained": active_groups})
                bar.update(1)
            if phase == 1 and not warming:
                level = options.threshold * min(1.0, (progress + 1 / n_epochs - options.warmup)
                                                / (options.ramp - options.warmup))
                _prune(model, size_sum / n_chunks, level, free_rows)
            if verbose:
                bar.set_postfix(phase=phase, mse=f"{history[-1]['mse']:.2e}",
                                terms=int(model.support.sum()))
    bar.close()
    return history


@torch.no_grad()
def _prune(model, mean_size, level, free_rows):
    """Drop free terms whose gate is closed or whose mean |Xi| over the epoch is below
    ``level`` (mean of |Xi|: a coefficient that changes sign is not pruned)."""
    gate = model.gates(stochastic=False)
    drop = ((mean_size < level) | (gate <= 0)) & model.support & free_rows[:, None]
    model.support &= ~drop


def _online_pass(model, theta, xdot, weights, inputs, noise_var, starts, window, options,
                 bayes, bar):
    """Read the series once in time order; the main module adapts to every window and
    the coefficients are recorded as it goes (chunk means and spreads)."""
    main = [p for name, p in model.named_parameters()
            if p.requires_grad and not name.startswith((*_HYPERNETWORK, "generator.codes"))]
    opts = [torch.optim.AdamW(main, lr=options.learning_rate,
                              weight_decay=options.weight_decay, amsgrad=True)]
    if model.generator.codes is not None:
        opts.append(torch.optim.SparseAdam([model.generator.codes.weight],
                                           lr=options.learning_rate * _CODE_LR))
    means, stds, history, previous = [], [], [], None
    for start in starts:
        sl = slice(start, start + window)
        for _ in range(options.online_steps):
            terms, xi_c, _ = _window_loss(model, theta, xdot, weights, inputs, noise_var,
                                          None, previous, False, start,
                                          min(start + window, theta.shape[1]),
                                          options.threshold)
            loss = terms["mse"] + options.kl_weight * terms["kl"] \
                + bayes * _refit_roughness(terms, options)
            for opt in opts:
                opt.zero_grad(set_to_none=True)
            loss.backward()
            nn.utils.clip_grad_norm_(main, options.grad_clip)
            for opt in opts:
                opt.step()
            history.append({"phase": 2, "loss": float(loss.detach()),
                            "mse": float(terms["mse"].detach())})
        bar.update(1)
        with torch.no_grad():
            mean, _, _ = model.window(inputs[..., sl], 0, None, start=start)
            draws, _, _ = model.window(inputs[..., sl], 16, None, start=start)
        means.append(mean[0])
        stds.append(draws.std(dim=0))
        previous = mean[:, -1:]
    model.track_mean = torch.cat(means)
    model.track_std = torch.cat(stds)
    return history
