"""The dynamic SINDy loss and its two-phase training (support, then refit)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np
import torch
from torch import nn
from tqdm.auto import tqdm

from .._core.threads import single_thread
from .._core.timing import timed
from .decisions import between_phases
from .flat_adam import FlatAdam
from .numpy_step import NumpyStep, supported

_EPS = torch.finfo(torch.float32).eps
TV_SHARE = 0.5  # share of total variation in the roughness (see roughness)


@dataclass(frozen=True)
class TrainingOptions:
    """How stage one is trained. Every weight acts on normalised quantities.

    Derivatives are scaled to unit RMS per state and library columns to unit RMS, so
    a coefficient's normalised size is the share of its equation's RMS derivative it
    explains. That makes the defaults below independent of units and series length.

    Attributes
    ----------
    support_steps, refit_steps : int
        Optimiser steps of phase one (find the support) and phase two (refit).
    learning_rate : float
        Adam's initial step size; a cosine schedule decays it within each phase.
    threshold : float
        Final pruning threshold: a term whose mean |coefficient| over time explains
        less than this fraction of its equation's RMS derivative is removed.
    prune_every : int
        Steps between pruning checks.
    warmup : float
        Fraction of phase one fitted without sparsity or pruning.
    ramp : float
        Fraction of phase one at which the threshold, rising linearly from zero after
        the warm-up, reaches ``threshold``.
    kl_weight : float
        Weight of the KL divergence relative to the ELBO. The derivative misfit is a
        Gaussian likelihood whose variance is the derivative noise estimated from the
        data, so with ``kl_weight=1`` the posterior spread follows the noise level
        (narrow on clean data, wide on noisy data) instead of a hand-set balance.
    sparsity : float
        Weight of the sparsity penalty in phase one (off in phase two): a reweighted
        L1 (log) penalty whose slope is 1 at zero and falls as a term grows past
        ``threshold``, so it removes small terms without shrinking the ones that stay.
    smoothness : float
        Weight of the normalised roughness (:func:`roughness`: half the absolute
        second differences, i.e. changes of slope) in phase one.
    refit_smoothness : float
        Weight of the normalised roughness in phase two, scaled by the noise level
        (derivative noise variance times the number of increments, between 0.01 and
        1): clean data are fitted almost exactly, noisy data are smoothed.
    grad_clip : float
        Maximum gradient norm.
    """

    support_steps: int = 800
    refit_steps: int = 700
    learning_rate: float = 3e-3
    threshold: float = 0.05
    prune_every: int = 25
    warmup: float = 0.25
    ramp: float = 0.75
    kl_weight: float = 1.0
    sparsity: float = 0.1
    smoothness: float = 0.3
    refit_smoothness: float = 2.0
    grad_clip: float = 1.0

    def __post_init__(self):
        check_nonnegative_fields(self)
        if self.prune_every < 1:
            raise ValueError(f"TrainingOptions.prune_every must be >= 1; got {self.prune_every}")
        if not 0 <= self.warmup < self.ramp <= 1:
            raise ValueError("TrainingOptions needs 0 <= warmup < ramp <= 1; got "
                             f"warmup={self.warmup}, ramp={self.ramp}")
        if self.learning_rate <= 0:
            raise ValueError("TrainingOptions.learning_rate must be > 0; "
                             f"got {self.learning_rate}")


def check_nonnegative_fields(options, skip=()) -> None:
    """Every field of an options dataclass (bar ``skip``) is an int or number >= 0."""
    name = type(options).__name__
    for f in fields(options):
        if f.name in skip:
            continue
        value = getattr(options, f.name)
        if f.type == "int":
            if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
                raise ValueError(f"{name}.{f.name} must be an int >= 0; got {value!r}")
        elif (isinstance(value, bool) or not isinstance(value, int | float)
              or not math.isfinite(value) or value < 0):
            raise ValueError(f"{name}.{f.name} must be a number >= 0; got {value!r}")


def make_training_options(given, cls=None, generator="timevae"):
    """Validated training options of class ``cls`` (the one ``generator`` trains with)."""
    cls = cls or TrainingOptions
    if given is None:
        return cls()
    if isinstance(given, cls):
        return given
    if isinstance(given, dict):
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(given) - names)
        if unknown:
            raise TypeError(f"Unknown training option(s) {unknown} for generator "
                            f"{generator!r}; valid options are {sorted(names)}.")
        return cls(**given)
    raise TypeError(f"training for generator {generator!r} must be a {cls.__name__}, a dict "
                    f"or None; got {type(given).__name__}.")


class CoefficientModel(nn.Module):
    """Xi(t) = support * (constants + time_varying * generator(x)), normalised units.

    A constant can be pinned (:meth:`pin_constant`): it then keeps its value whatever
    the optimiser does (the exact model's estimate, see ``decisions.adopt_structure``).
    """

    def __init__(self, generator, constants, support, time_varying):
        super().__init__()
        self.generator = generator
        self.constants = nn.Parameter(constants.clone())
        self.register_buffer("support", support.clone())
        self.register_buffer("time_varying", time_varying.clone())
        self.register_buffer("pin_mask", torch.zeros_like(support, dtype=torch.bool))
        self.register_buffer("pin_value", torch.zeros_like(constants))
        self.restored = []  # (equation, term) pairs returned by restore_terms

    def effective_constants(self) -> torch.Tensor:
        """The constants, pinned ones replaced by their pinned values."""
        return torch.where(self.pin_mask, self.pin_value, self.constants)

    @torch.no_grad()
    def pin_constant(self, i: int, j: int, value: float) -> None:
        """Fit term ``j`` of equation ``i`` as the constant ``value``, not trained."""
        self.time_varying[i, j] = 0.0
        self.pin_mask[i, j] = True
        self.pin_value[i, j] = value
        self.constants[i, j] = value

    @torch.no_grad()
    def mean_blocks(self, inputs):
        """Yield (start, stop, Xi) with Xi (stop - start, n, F): the mean coefficients
        over the whole series, block by block."""
        xi, _ = self(inputs, 0)
        yield 0, xi.shape[1], xi[0]

    @torch.no_grad()
    def restore_constant(self, i: int, j: int) -> None:
        """Put term ``j`` of equation ``i`` back in the support, as a constant."""
        self.support[i, j] = True
        self.time_varying[i, j] = 0.0

    @torch.no_grad()
    def freeze_constant(self, i: int, j: int, value: float) -> None:
        """Fit term ``j`` of equation ``i`` as the constant ``value`` from now on."""
        self.time_varying[i, j] = 0.0
        self.constants[i, j] = value

    @torch.no_grad()
    def free_variation(self, i: int, j: int) -> None:
        """Let term ``j`` of equation ``i`` vary."""
        self.time_varying[i, j] = 1.0

    def forward(self, inputs, n_samples: int):
        series, kl = self.generator.sample(inputs, n_samples)
        n_states, n_features = self.constants.shape
        series = series.reshape(series.shape[0], series.shape[1], n_states, n_features)
        xi = self.support * (self.effective_constants() + self.time_varying * series)
        return xi, kl


def least_squares_constants(theta, xdot, support):
    """Constant-coefficient fit per equation on its support (normalised, small ridge)."""
    n_states, n_features = support.shape
    a = theta.reshape(-1, n_features)
    b = xdot.reshape(-1, n_states)
    out = torch.zeros(n_states, n_features, dtype=theta.dtype, device=theta.device)
    for i in range(n_states):
        cols = torch.nonzero(support[i]).flatten()
        if len(cols) == 0:
            continue
        ai = a[:, cols]
        gram = ai.T @ ai + 1e-6 * a.shape[0] * torch.eye(len(cols), dtype=a.dtype,
                                                         device=a.device)
        out[i, cols] = torch.linalg.solve(gram, ai.T @ b[:, i])
    return out


def loss_terms(model, theta, xdot, weights, inputs, noise_var, threshold, free_rows):
    """Loss terms on normalised data.

    ``weights`` (n_traj, n_times, n_states) are per-sample likelihood weights (inverse
    relative noise variance of the derivative); ``noise_var`` the noise variance.
    """
    xi, kl = model(inputs, 1)
    pred = torch.einsum("btf,stnf->sbtn", theta, xi)
    mse = torch.mean(weights[None] * (pred - xdot[None]) ** 2)
    # ELBO in MSE units: sum r^2 / (2 s^2) + KL  ->  mse + 2 s^2 KL / N
    kl = 2.0 * noise_var * kl / xdot.numel()
    active = model.support.to(xi.dtype)
    n_active = active.sum().clamp_min(1.0)
    size = xi.abs().mean(dim=(0, 1)) * active  # mean |Xi| over time, per term
    rough = (roughness(xi, model.generator.spacing) * active).sum() / n_active
    mean_abs = size.sum() / n_active
    # relative to the coefficients' size, but never to less than the pruning
    # threshold: a coefficient that averages about zero must still be free to vary
    rough = rough / torch.clamp(mean_abs.detach(), min=threshold)
    # A Laplace prior on slope changes in ELBO units would weigh the roughness by the
    # noise variance times the number of increments: clean data are fitted exactly.
    bayes = noise_var * xi.shape[1] * n_active.detach() / xdot.shape[-1]
    # log penalty (reweighted L1): slope 1 at zero, 1/(1 + size/threshold) beyond, so
    # small terms are pushed hard and the terms that stay are barely shrunk
    l1 = (threshold * torch.log1p(size / threshold) * free_rows[:, None]).sum()
    return {"mse": mse, "kl": kl, "l1": l1, "rough": rough,
            "rough_bayes": min(1.0, max(0.01, float(bayes)))}


def total_loss(terms, l1_weight, rough_weight, kl_weight, rough_scaled):
    """The training loss from :func:`loss_terms` (tensors or floats): ``mse + kl_weight
    kl + l1_weight l1 + rough_weight [rough_bayes] rough``, the roughness scaled by
    ``rough_bayes`` only if ``rough_scaled`` (the refit); the refit has no l1 term."""
    scale = terms["rough_bayes"] if rough_scaled else 1.0
    reg = rough_weight * scale * terms["rough"]
    if not rough_scaled:
        reg = l1_weight * terms["l1"] + reg
    return terms["mse"] + kl_weight * terms["kl"] + reg


def roughness(track: torch.Tensor, spacing: torch.Tensor | None = None) -> torch.Tensor:
    """Smoothness penalty of both generators, per trailing entry: half the mean absolute
    second difference along time (dim 1) plus ``TV_SHARE`` of the mean absolute first
    difference (total variation).

    Total variation alone penalises amplitude: it flattens peaks and troughs (on
    prey-only LV at 1% noise the hidden state sat 0.059 above the true minima). Slope
    changes do not: clipping a peak does not lower them. A pure slope-change penalty,
    though, lets constant coefficients drift linearly (a constant oscillator's
    coefficient drifted by 8.7%, and the switch and Lorenz bars failed), so half of the
    total variation stays: minima now within 0.033, the other bars unchanged. A jump
    costs 1.5 times what total variation alone charged; sample-to-sample noise is
    penalised as before.

    ``spacing`` (len - 1,) are the times between consecutive points of the track (None:
    equal). Then the second differences are divided differences in units of the mean
    spacing, each weighted by the time it stands for: a prior per unit time, not per
    sample (equal spacing gives the plain differences). Total variation needs no
    change: it is the same whatever the sampling.
    """
    if track.shape[1] < 3:
        return track.new_zeros(track.shape[2:])
    first = track[:, 1:] - track[:, :-1]
    if spacing is None:
        second = (track[:, 2:] - 2 * track[:, 1:-1] + track[:, :-2]).abs()
    else:
        # steps under a thousandth of the mean count as that: two samples nearly at the
        # same time share one position in float32 (a zero step, 0/0 slopes otherwise)
        h = (spacing / spacing.mean()).clamp_min(1e-3).to(track.dtype)
        h = h.reshape(1, -1, *([1] * (track.dim() - 2)))
        slope = first / h
        width = h[:, 1:] + h[:, :-1]
        second = (2 * (slope[:, 1:] - slope[:, :-1]) / width).abs() * (width / 2)
    return 0.5 * second.mean(dim=(0, 1)) + TV_SHARE * first.abs().mean(dim=(0, 1))


def _cosine(step, total, lr0, lr_min):
    return lr_min + 0.5 * (lr0 - lr_min) * (1 + math.cos(math.pi * min(step / max(total, 1), 1)))


@timed("stage one: generator")
def train(model, theta, xdot, weights, inputs, noise_var, free_rows,
          options: TrainingOptions, verbose: bool, decide=None):
    """Two-phase training in place; returns the loss history (one dict per step).
    ``decide(model)``, if given, runs between the phases, after the restoring checks."""
    history = []
    params = [p for p in model.parameters() if p.requires_grad]
    data = (theta, xdot, weights, inputs, noise_var, free_rows)
    # Adam's arithmetic on one flat buffer (flat_adam.py): the same coefficients as
    # torch.optim.Adam(foreach=True), a tenth of a step less on a CPU
    opt = FlatAdam(params, lr=options.learning_rate)
    bar = tqdm(total=options.support_steps + options.refit_steps, disable=not verbose,
               desc="dynamic SINDy", leave=False)
    try:
        for phase, steps in ((1, options.support_steps), (2, options.refit_steps)):
            if phase == 2:
                between_phases(model, theta, xdot, weights, inputs, options.threshold,
                               free_rows, decide)
                opt.release()
                opt = FlatAdam(params, lr=options.learning_rate / 3)
            history += _train_phase(model, opt, phase, steps, data, options, bar, verbose)
    finally:  # the parameters own their storage again, whatever happened
        opt.release()
        bar.close()
    return history


def _train_phase(model, opt, phase, steps, data, options, bar, verbose):
    """``steps`` optimiser steps of one phase (learning rate on a cosine schedule)."""
    theta, xdot, weights, inputs, noise_var, free_rows = data
    # on a CPU the loss and its gradient written out in numpy (numpy_step.py): the same
    # model and loss without the framework's overhead per operation, on one thread
    if supported(model, theta, xdot, weights, inputs):
        by_hand = NumpyStep(model, theta, xdot, weights, inputs, noise_var, options.threshold,
                            free_rows)
        with single_thread():
            return _steps(model, opt, phase, steps, data, options, bar, verbose, by_hand)
    return _steps(model, opt, phase, steps, data, options, bar, verbose, None)


def _steps(model, opt, phase, steps, data, options, bar, verbose, by_hand):
    theta, xdot, weights, inputs, noise_var, free_rows = data
    history, lr0 = [], opt.lr
    for step in range(steps):
        opt.lr = _cosine(step, steps, lr0, lr0 * 1e-2)
        warming = phase == 1 and step < options.warmup * steps
        if phase == 1:
            # warm-up: fit first, so a term whose time average is small but whose
            # variation matters is not pruned before the generator learns it
            l1_weight, rough_weight = (0.0 if warming else options.sparsity), options.smoothness
        else:
            # Refit: smoothing follows the noise level (exact fits on clean data),
            # capped at the normalised weight so rich variation is not flattened.
            l1_weight, rough_weight = 0.0, options.refit_smoothness
        if by_hand is not None:
            terms = by_hand(l1_weight, rough_weight, options.kl_weight,
                            rough_scaled=phase == 2)
            loss = total_loss(terms, l1_weight, rough_weight, options.kl_weight, phase == 2)
        else:
            terms = loss_terms(model, theta, xdot, weights, inputs, noise_var,
                               options.threshold, free_rows.to(theta.dtype))
            loss = total_loss(terms, l1_weight, rough_weight, options.kl_weight, phase == 2)
            opt.zero_grad()
            loss.backward()
        opt.step(max_norm=options.grad_clip)
        if ((step + 1) % options.prune_every == 0 and not warming
                and (phase == 1 or step < steps // 2)):
            # phase one: the threshold rises after the warm-up; phase two: terms the
            # refit shrinks below the full threshold are dropped early in the phase.
            start = options.warmup * steps
            ramp = 1.0 if phase == 2 else (step + 1 - start) / max(
                1.0, (options.ramp - options.warmup) * steps)
            _prune(model, inputs, options.threshold * min(1.0, ramp), free_rows)
        record = {k: float(v.detach()) if torch.is_tensor(v) else v for k, v in terms.items()}
        record.update(phase=phase, loss=float(loss.detach()) if torch.is_tensor(loss) else loss)
        history.append(record)
        bar.update(1)
        if verbose and step % 50 == 0:
            bar.set_postfix(phase=phase, mse=f"{record['mse']:.2e}",
                            terms=int(model.support.sum()))
    return history


@torch.no_grad()
def _prune(model, inputs, level, free_rows):
    xi, _ = model(inputs, 0)
    size = xi[0].abs().mean(dim=0)  # mean |Xi| over time: sign changes do not cancel
    drop = (size < level) & model.support & free_rows[:, None]
    if drop.any():
        model.support &= ~drop
