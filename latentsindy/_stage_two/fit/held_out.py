"""Held-out scoring of a refined system (:func:`cross_validate`).

Segments are held out in interleaved folds (every ``n_folds``-th segment); with their
data removed, a held-out segment is still bridged by integration from its neighbours
(continuity), so its misfit measures how well the fitted system reproduces data it was
not fitted to, for chaotic systems too. A panel of short recordings is held out by
whole recordings instead, each fitted only in its initial values with the law from the
others (:func:`by_recording`); a recording of fewer segments than folds, by interleaved
samples (:func:`by_sample`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..._core.parallel import map_on
from ..._core.timing import timed
from .refine import Fit, Problem
from .shooting import BlowUp

# Recordings of at most this many segments are held out whole (:func:`by_recording`).
SHORT_RECORDING = 2


@timed("held-out score")
def cross_validate(problem: Problem, fit: Fit, max_iterations=10):
    """Held-out misfit by interleaved folds (mean, standard error, per unit errors):
    of segments, each bridged by its neighbours; where every recording is short (a
    panel: :func:`by_recording`), of whole recordings; in a recording of fewer segments
    than folds (:func:`by_sample`), of samples. Each fold starts from ``fit`` and is
    refitted without its data (independently: on a CPU a second core takes some of the
    folds, the same errors)."""
    if by_recording(problem):
        return _recording_folds(problem, fit, max_iterations)
    if by_sample(problem):
        return _sample_folds(problem, fit, max_iterations)
    folds = problem.options.n_folds
    fold_of = np.concatenate([np.arange(g.n_segments) % folds for g in problem.groups])
    helds = [fold_of == f for f in range(folds)]
    helds = [held for held in helds if held.any() and not held.all()]
    return _pooled(_refitted(problem, fit, helds, problem.segment_errors, max_iterations))


def by_recording(problem: Problem) -> bool:
    """Whether the held-out units are whole recordings: at least ``n_folds`` of them,
    none longer than ``SHORT_RECORDING`` segments. Within such a recording a held-out
    segment is bridged from a neighbour of a few noisy samples, so an exact law
    misses it by several noise variances (epidemic panels of 20 x 11 samples: 5-19, a
    mean over segments dominated by a few at 25-50) and the check loses its power."""
    return (len(problem.groups) >= problem.options.n_folds
            and all(g.n_segments <= SHORT_RECORDING for g in problem.groups))


def by_sample(problem: Problem) -> bool:
    """Whether the held-out units are samples: fewer segments than folds (a recording
    of a few dozen samples or less, not a panel). Held out by segments, each fold would
    refit the law on half or two thirds of the samples and predict the rest from a
    neighbour's few: an exact law scored 20 noise variances on an epidemic wave sampled
    12 times (13 samples, two segments), and the check had no power."""
    return not by_recording(problem) and problem.n_segments < problem.options.n_folds


def _sample_folds(problem: Problem, fit: Fit, max_iterations):
    """Leave samples out: fold ``f`` holds out every ``n_folds``-th sample of each
    recording from its ``f``-th on, bridged by integration from the samples on both
    sides; a sample's error is its squared misfit (noise variances, averaged over the
    observed states). The errors come recording by recording, in time order."""
    folds = problem.options.n_folds
    width = max(g.mask.shape[1] for g in problem.groups)
    index = np.full((problem.n_segments, width), -1)  # the sample's in its recording
    ident = np.full((problem.n_segments, width), -1)  # over all recordings
    offsets = np.cumsum([0] + [len(t) for t in problem.times])
    for g in problem.groups:
        rows = slice(g.first, g.first + g.n_segments)
        index[rows, :g.mask.shape[1]] = g.sample_index
        ident[rows, :g.mask.shape[1]] = np.where(g.sample_index >= 0,
                                                 g.sample_index + offsets[g.trajectory], -1)
    helds = [(index >= 0) & (index % folds == f) for f in range(folds)]
    helds = [held for held in helds if held.any()]
    by_fold = _refitted(problem, fit, helds, problem.sample_errors, max_iterations)
    order = np.argsort(np.concatenate([ident[held] for held in helds]))
    return _pooled([np.concatenate(by_fold)[order]])


def _recording_folds(problem: Problem, fit: Fit, max_iterations):
    """Leave recordings out: each fold refits the law without its recordings, then fits
    only their initial values (observed and hidden) to their own data with the law
    fixed, as a new subject would be fitted. A recording's error is its misfit per
    degree of freedom (samples times observed states, less one initial value per
    state): about 1 for the right law, whose only freedom there is where it starts.
    The errors come in the recordings' order."""
    folds = problem.options.n_folds
    fold_of = np.concatenate([np.full(g.n_segments, k % folds)
                              for k, g in enumerate(problem.groups)])
    helds = [fold_of == f for f in range(folds)]

    def fold(held):
        try:
            part = _without(problem, fit, held, max_iterations)
            law = dataclasses.replace(part.system, free=np.zeros_like(part.system.free))
            own = problem.fit(law, part.starts.copy(), held.astype(float), max_iterations,
                              penalties=(fit.rho,), resolution=0.0)
            return problem.recording_errors(own, held)
        except BlowUp:
            return np.full(sum(bool(held[g.first]) for g in problem.groups), np.inf)

    by_fold = map_on(problem.options.device, fold, helds)
    errors = np.empty(len(problem.groups))  # in the recordings' order
    for f, found in enumerate(by_fold):
        errors[f::folds] = found
    return _pooled([errors])


def _refitted(problem: Problem, fit: Fit, helds, errors, max_iterations):
    """For every fold's ``held`` units, ``errors(fit refitted without them, held)``; one
    inf per held unit where the refit blows up."""
    def fold(held):
        try:
            return errors(_without(problem, fit, held, max_iterations), held)
        except BlowUp:
            return np.full(int(held.sum()), np.inf)

    return map_on(problem.options.device, fold, helds)


def _without(problem: Problem, fit: Fit, held, max_iterations) -> Fit:
    """``fit`` refitted without the ``held`` segments' data, converged fully (no
    resolution): the fold starts from the fit that saw its held-out data, and stopping
    early would leave it nearer that fit, scoring optimistically (a runner-up on
    prey-only LV scored 0.984 instead of 1.01, inside the winner's band)."""
    return problem.fit(fit.system, fit.starts.copy(), (~held).astype(float), max_iterations,
                       penalties=(fit.rho,), resolution=0.0)


def _pooled(errors):
    errors = np.concatenate(errors) if errors else np.array([np.inf])
    if not np.all(np.isfinite(errors)):
        return np.inf, np.inf, errors
    return float(errors.mean()), float(errors.std(ddof=1) / np.sqrt(len(errors))), errors
