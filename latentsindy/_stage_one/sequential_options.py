"""Options of the window-by-window training (dynamic HyperSINDy), validated once."""

from __future__ import annotations

from dataclasses import dataclass

from .training import check_nonnegative_fields

MODES = ("alternate", "joint", "online")


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
        up to whole passes over the series (epochs), at least ``min_epochs``. The
        refit starts from a changed structure (the exact model's choice, pinned
        constants) and needs twice the support phase's steps: Lorenz with sigma(t) a
        7-frequency Fourier series, T=10,000: sigma R^2 0.80 after 700 steps, 0.96
        after 1400. Long series reach ``min_epochs`` first and are not affected.
    min_epochs : int
        Fewest passes over the series per phase (long series need few).
    learning_rate, weight_decay, lr_decay : float
        AdamW (amsgrad) step size and weight decay; the step size is multiplied by
        ``lr_decay`` after every optimiser step.
    threshold : float
        Final pruning threshold on a term's mean absolute coefficient over time (a share of
        its equation's RMS derivative), reached by a linear rise after the warm-up.
    warmup, ramp : float
        Fractions of phase one without pruning (with one latent per window, so the
        coefficients are constant within a window), and at which the threshold is full.
    sparsity : float
        Weight of the relaxed-L0 penalty (expected number of active terms per
        equation) in phase one.
    l1 : float
        Weight of the reweighted-L1 (log) penalty on each term's mean absolute value of Xi, per
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
        Weights of the normalised roughness, as in :class:`TrainingOptions`; in
        the refit, ``refit_smoothness`` acts on terms that vary together with another
        term of their equation: only a smoothness penalty keeps such terms from
        trading off with state-dependent wiggles (Lorenz's sigma(t) in ``-sigma x +
        sigma y``, T=10,000, 1% noise, three seeds: R^2 0.97, 0.94, 0.76 with 2,
        0.997, 0.996, 0.996 with 10).
    lone_smoothness : float
        Refit weight of the roughness on a term that is its equation's only varying
        term: identified pointwise by the data, it needs smoothing only against noise,
        and a strong smoothness prior (total variation about one coefficient size)
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
    refit_steps: int = 1400
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
