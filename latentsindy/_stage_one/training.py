"""timeVAE's two-phase training (support, then refit) of the loss of :mod:`.loss`."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, fields

import numpy as np
import torch
from tqdm.auto import tqdm

from .._core.budget import before_a_phase
from .._core.threads import flush_denormals, single_thread
from .._core.timing import timed
from .decisions import between_phases
from .flat_adam import FlatAdam
from .loss import loss_terms, total_loss

__all__ = ["TrainingOptions", "check_nonnegative_fields",
           "make_training_options", "train"]


@dataclass(frozen=True)
class TrainingOptions:
    """How stage one is trained. Every weight acts on normalised quantities.

    Derivatives are scaled to unit RMS per state and library columns to unit RMS, so
    a coefficient's normalised size is the share of its equation's RMS derivative it
    explains. That makes the defaults below independent of units and series length.

    Attributes
    ----------
    support_steps, refit_steps : int
        Optimiser steps of phase one (find the support) and phase two (refit). The
        refit starts from phase one's network on a structure already decided, with its
        own cosine schedule (and its own pruning checks in its first half); its loss
        settles within a few hundred steps (prey-only Lotka-Volterra: within 1% of its
        end by step 300 of 700). 400 refit steps instead of 700 moved the stage-one
        benchmark's R^2 of the varying coefficients by at most 0.001. Where stage two
        follows, it fits the laws to the data themselves: the same laws to the last
        digit in 61 of the quick benchmark tables' 63 calls, every count of the full
        tables the same but Lorenz seen through x (its second hidden state is read
        from these coefficients): one exact call fewer at 1% noise, one more at 5%.
    learning_rate : float
        Adam's initial step size; a cosine schedule decays it within each phase.
    threshold : float
        Final pruning threshold: a term whose mean absolute coefficient over time explains
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
        Weight of the normalised roughness (:func:`.loss.roughness`: shares of the
        absolute second and first differences) in phase one.
    refit_smoothness : float
        Weight of the normalised roughness in phase two, scaled by the noise level
        (derivative noise variance times the number of increments, between 0.01 and
        1): clean data are fitted almost exactly, noisy data are smoothed.
    grad_clip : float
        Maximum gradient norm.
    """

    support_steps: int = 800
    refit_steps: int = 400
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
    # Adam with clipping on one flat buffer (flat_adam.py): torch.optim.Adam's update,
    # one compiled loop on a CPU, torch's foreach kernels (to the bit) elsewhere
    opt = FlatAdam(params, lr=options.learning_rate)
    bar = tqdm(total=options.support_steps + options.refit_steps, disable=not verbose,
               desc="dynamic SINDy", leave=False)
    try:
        begin = time.perf_counter()
        for phase, steps in ((1, options.support_steps), (2, options.refit_steps)):
            if phase == 2:
                # max_time: the second phase runs whatever the budget; the decisions
                # before it keep its time (at the first phase's pace) in reserve
                pace = (time.perf_counter() - begin) / max(options.support_steps, 1)
                with before_a_phase(pace * steps):
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
    # on a CPU the loss and its gradient written out (numpy_step.py, its layers compiled
    # by numba): the same model and loss without the framework's overhead per
    # operation, on one thread. Imported here: numba loads at the first training
    from .numpy_step import NumpyStep, supported

    if supported(model, theta, xdot, weights, inputs):
        by_hand = NumpyStep(model, theta, xdot, weights, inputs, noise_var, options.threshold,
                            free_rows)
        with single_thread(), flush_denormals():
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
            sizes = None if by_hand is None else torch.from_numpy(by_hand.term_sizes())
            _prune(model, inputs, options.threshold * min(1.0, ramp), free_rows, sizes)
        record = {k: float(v.detach()) if torch.is_tensor(v) else v for k, v in terms.items()}
        record.update(phase=phase, loss=float(loss.detach()) if torch.is_tensor(loss) else loss)
        history.append(record)
        bar.update(1)
        if verbose and step % 50 == 0:
            bar.set_postfix(phase=phase, mse=f"{record['mse']:.2e}",
                            terms=int(model.support.sum()))
    return history


@torch.no_grad()
def _prune(model, inputs, level, free_rows, size=None):
    """Drop the free terms whose mean |Xi| over time (``size``, (n, F): sign changes do
    not cancel; None: the model's, at the latent's mean) is below ``level``."""
    if size is None:
        xi, _ = model(inputs, 0)
        size = xi[0].abs().mean(dim=0)
    drop = (size < level) & model.support & free_rows[:, None]
    if drop.any():
        model.support &= ~drop
