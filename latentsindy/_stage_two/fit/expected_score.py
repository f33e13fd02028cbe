"""What a right system would score: the held-out score's reference, simulated.

A held-out segment is predicted from a start that its neighbours pin down, so a right
system scores about 1 noise variance there: the noise, and little else. Where the
segments are few and short (a few samples per cycle), the start is pinned by a
handful of noisy samples and the prediction carries its uncertainty too: an exact law
then scores several noise variances (a dozen samples per epidemic wave held out by
segments: up to hundreds), and "expected ~1" would call a right law wrong. (A panel
of short recordings is held out by recording, :func:`.held_out.by_recording`, and a
recording of fewer segments than folds by samples, :func:`.held_out.by_sample`: there
the reference is about 1-2.3.)

:func:`expected_score` measures that reference for the chosen system by a parametric
bootstrap: data simulated from the fitted system at the recording's own times (its
trajectories plus noise of the estimated level, AR(1)-correlated where the noise was
found to be, and growing with the signal where it plainly does, as counts' does:
:mod:`latentsindy._core.noise_shape`), refitted from the fitted system and scored by
the same folds. Its mean
over a few replicates is the score that this system would get if it were the truth;
a real score well above it says that it is not.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import torch

from ..._core.budget import spent
from ..._core.local_fits import is_uniform
from ..._core.noise_shape import level_profile
from .held_out import cross_validate
from .refine import Fit, Problem
from .shooting import BlowUp

REPLICATES = 4  # simulated data sets; the reference is their mean score
# what the discovery's max_time leaves out when it is spent before the reference starts
REFERENCE = "a right system's held-out score, simulated (the reference)"
SEED = 20261129  # fixed: the same data give the same reference
MIN_SCORED = 2  # replicates refitted and scored, at least
# A replicate's refit starts at the system and starts that simulated it, so it misfits
# the data by their noise at most; one that ends further than this many times the
# noise's own misfit away has lost the truth it started at (the continuity penalty
# traded the data away, or the fit stopped in a spike's steep valley), and its score
# measures the optimiser, not the sampling. Then this system gives no reference at
# all: the replicates left would be the easy ones. (Hindmarsh-Rose at 1%: such refits
# ended 54 times the noise, and the "right system's" reference read 453.)
REFITTED = 2.0


def expected_score(problem: Problem, fit: Fit, replicates: int = REPLICATES) -> float | None:
    """Mean held-out score of ``fit``'s system on data simulated from it (the same
    times, segments, folds and noise level); None when it cannot be simulated (the
    fitted segments do not meet, :attr:`.refine.Fit.continuous`, or blow up), when a
    replicate's refit misses its data by more than ``REFITTED`` times their noise, when
    fewer than ``MIN_SCORED`` replicates could be refitted and scored, or when
    ``max_time`` is spent."""
    if spent(REFERENCE):  # every fit would stop before its first step: no reference
        return None
    if not fit.continuous:
        # no trajectory of its system, so no data a right system would give: the
        # replicates' segments would be torn too, and their refits would trade the data
        # for continuity (Hindmarsh-Rose at 1%, draw 0: gaps of 11 noise levels; refits
        # of the fitted system on its own simulated data missed them by 57 noise
        # variances per sample, and the "right system's" reference read 453)
        return None
    model = problem.trajectories(fit)
    if not all(np.all(np.isfinite(m[:, :problem.n_obs])) for m in model):
        return None
    rng = np.random.default_rng(SEED)
    shape = (level_profile(problem.observed)
             if all(is_uniform(t) for t in problem.times if len(t) > 2)
             else [np.ones_like(x) for x in problem.observed])
    scores = []
    for _ in range(replicates):
        data = [m[:, :problem.n_obs] + _noise(rng, t, problem) * s
                for m, t, s in zip(model, problem.times, shape, strict=True)]
        synthetic = _with_data(problem, data)
        try:
            truth = synthetic.equations(fit.system, fit.starts, np.ones(problem.n_segments),
                                        fit.rho, jacobian=False).data_cost
            refit = synthetic.fit(fit.system, fit.starts.copy(), resolution=0.0,
                                  penalties=(fit.rho,))
            if not refit.data_cost <= REFITTED * truth:
                return None  # the system cannot be refitted on data simulated from it
            score, _, _ = cross_validate(synthetic, refit)
        except (BlowUp, np.linalg.LinAlgError, ValueError):
            continue
        if np.isfinite(score):
            scores.append(score)
    # one surviving replicate is no reference (those that blew up may be the hard ones)
    return float(np.mean(scores)) if len(scores) >= MIN_SCORED else None


def _noise(rng, t, problem: Problem) -> np.ndarray:
    """Noise at the estimated level for samples at times ``t``: white, or AR(1) with
    the estimated correlation per median step (``problem.phi``)."""
    e = rng.standard_normal((len(t), problem.n_obs)) * problem.sigma
    phi = np.broadcast_to(np.asarray(problem.phi, float), (problem.n_obs,))
    if not np.any(phi > 0) or len(t) < 2:
        return e
    dt = float(np.median(np.concatenate([np.diff(tt) for tt in problem.times])))
    out = e.copy()
    for k in range(1, len(t)):
        a = phi ** ((t[k] - t[k - 1]) / dt)
        out[k] = a * out[k - 1] + np.sqrt(1 - a**2) * e[k]
    return out


def _with_data(problem: Problem, data) -> Problem:
    """``problem`` (the same segments, grid, scales and noise level) with other data."""
    other = copy.copy(problem)
    other.observed = [np.asarray(x, float) for x in data]
    groups = []
    for g in problem.groups:
        obs = g.observed.clone()
        idx = g.sample_index
        mask = g.mask.numpy()
        obs[torch.as_tensor(mask)] = torch.as_tensor(
            other.observed[g.trajectory][idx[mask]], dtype=obs.dtype)
        groups.append(replace(g, observed=obs))
    other.groups = groups
    return other
