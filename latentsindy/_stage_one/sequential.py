"""Window-by-window training of sequential generators (dynamic HyperSINDy).

The options live in :mod:`.sequential_options`, the gated model and the
loss of one window in :mod:`.sequential_model`.

The series is read in time order in windows; the hypernetwork's state is carried from
one window to the next and detached (truncated backpropagation through time), so
memory is set by the window, not by the series length (the per-chunk latent offsets,
25 numbers per 10 steps, are the only per-sample parameters; a step updates its
window's rows only). The loss is the one of
:mod:`.loss` (derivative misfit, KL in ELBO units, sparsity, normalised
roughness) with the paper's HyperSINDy choices: relaxed-L0 (hard-concrete)
gates, a KL weight warmed up from ``kl_start``, AdamW with amsgrad and an exponential
learning-rate decay.
"""

from __future__ import annotations

import math
import time

import torch
from torch import nn
from tqdm.auto import tqdm

from .._core.budget import before_a_phase
from .._core.timing import timed
from ..generators.hypersindy import detach_state
from .decisions import between_phases, freeze_constant_terms
from .sequential_model import SequentialCoefficientModel, window_loss, windowed_constants
from .sequential_options import MODES, SequentialTrainingOptions

__all__ = ["MODES", "SequentialCoefficientModel", "SequentialTrainingOptions",
           "train_sequential", "windowed_constants"]

_HYPERNETWORK = ("generator.lstm", "generator.mlp", "generator.to_alpha")  # parameter names
_GATE_LR = 10.0  # gates learn ten times faster than the networks
_CODE_LR = 30.0  # per-chunk offsets: one update per epoch each, so large steps


def _refit_roughness(terms, options):
    return (options.refit_smoothness * terms["rough_shared"]
            + options.lone_smoothness * terms["rough_lone"])


def _epochs(steps, per_epoch, minimum):
    return max(minimum, math.ceil(steps / per_epoch)) if steps else 0


@timed("stage one: generator")
def train_sequential(model, theta, xdot, weights, inputs, noise_var, free_rows,
                     options: SequentialTrainingOptions, verbose: bool, decide=None):
    """Two-phase windowed training in place; returns the loss history (one dict per step).
    ``decide(model)``, if given, runs between the phases, after the restoring checks."""
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
    begin = time.perf_counter()
    for phase, n_epochs in ((1, epochs[0]), (2, epochs[1])):
        if phase == 2:
            # max_time, as timeVAE's training (training.py): the decisions before the
            # second phase keep its time (at the first phase's pace) in reserve
            second = (time.perf_counter() - begin) * n_epochs / max(epochs[0], 1)
            with torch.no_grad():  # closed variation gates: fitted as constants from now on
                model.time_varying *= (model.gates(False, model.log_alpha_var) > 0).to(
                    model.time_varying.dtype)
            model.log_alpha.requires_grad_(False)
            model.log_alpha_var.requires_grad_(False)
            with before_a_phase(second):
                freeze_constant_terms(model, theta, xdot, weights, inputs, var_cost,
                                      free_rows)
                between_phases(model, theta, xdot, weights, inputs, options.threshold,
                               free_rows, decide)
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
                terms, xi_c, state = window_loss(
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
            terms, xi_c, _ = window_loss(model, theta, xdot, weights, inputs, noise_var,
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
