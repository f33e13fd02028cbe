"""What the exact varying-coefficient model says about a finished fit: the band's
ingredients and the doubts.

The generator's posterior spread is the uncertainty of its own smooth fit given its
structure: it ignores smoothing bias at transitions and which structure is right, and
holds the truth at a median 21% of the samples of the paper's experiments. The exact
model (:mod:`.vcm_fit`) is a proper Bayesian posterior of the same coefficients on the
integral form of the data, with adaptive smoothness, whose noise level is estimated
from the data themselves. Its 95% interval, and those of every structure that explains
the data as well (within a Bayes factor of 20) and of the structure search's other
optimum where its climbs from two starts ended apart, make the band's core
(:class:`Assessment`: ``lower``/``upper``); :meth:`DynamicSINDy.coefficients` widens it
to hold the generator's mean and spread too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._core.doubt import Doubt
from .._core.timing import timed
from .structure import LOG_PRIOR_ODDS, EquationChoice, penalised, same_structure

BAND = 2.0  # standard deviations: a 95% interval
AGREE = 0.9  # R^2 of the generator's varying coefficient against the exact model's
MISFIT = 4.0  # exact model's noise variance over the measurement noise's
NEAR_THRESHOLD = 1.5  # a term this close to the threshold (in its multiples)


@dataclass(frozen=True)
class Assessment:
    """The exact model's posterior of a fit's coefficients (physical units) and its
    doubts.

    Attributes
    ----------
    mean, sd : ndarray (n_times, n_states, n_features)
        Posterior mean and standard deviation on the fitted structure (0 off support).
    lower, upper : ndarray (n_times, n_states, n_features)
        Union of the 95% intervals of the fitted structure, of every structure that
        explains the data as well and of the search's other optimum, if any (a term
        absent from one of them: 0 is inside).
    doubts : tuple of str
    """

    mean: np.ndarray
    sd: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    doubts: tuple[str, ...]


@timed("stage one: exact model")
def assess(exact, support, varying, choices, generator_mean, threshold, states, features,
           scale, generator_misfit=None) -> Assessment:
    """Assess a finished fit.

    Parameters
    ----------
    exact : VaryingCoefficients
    support, varying : (S, F) bool arrays of the fit
    choices : list of EquationChoice (None entries allowed), or None
        The search's result; without it the search is run here (for doubts only).
    generator_mean : (T, S, F) the generator's mean coefficients (physical units)
    threshold : float
    states, features : names
    scale : (S, F) physical units per normalised unit
    generator_misfit : (S,) generator's mean squared derivative misfit over the
        derivative noise variance, optional
    """
    n_times = generator_mean.shape[0]
    mean = np.zeros_like(generator_mean)
    sd = np.zeros_like(generator_mean)
    lower, upper = np.zeros_like(generator_mean), np.zeros_like(generator_mean)
    doubts = []
    basis = exact.basis
    for i, state in enumerate(states):
        fit = exact.fit(i, support[i], varying[i])  # an empty support too: xdot = 0
        m, s = _posterior(fit, basis, n_times, len(features))
        mean[:, i], sd[:, i] = m * scale[i], s * scale[i]
        lower[:, i], upper[:, i] = (m - BAND * s) * scale[i], (m + BAND * s) * scale[i]
        choice = choices[i] if choices is not None else None
        rivals = choice.rivals if choice is not None else ()
        # the search's other optimum, unless the fitted structure is that end itself
        apart = tuple(o for o in (choice.apart if choice is not None else ())
                      if not same_structure(o, fit))
        for structure in (*rivals, *apart):  # the band holds each one's interval too
            om, os_ = _posterior(structure, basis, n_times, len(features))
            lower[:, i] = np.minimum(lower[:, i], (om - BAND * os_) * scale[i])
            upper[:, i] = np.maximum(upper[:, i], (om + BAND * os_) * scale[i])
        for rival in rivals:
            doubts.append(Doubt("rival structure",
                                f"d{state}/dt: {_describe(rival, fit, features)} explains the "
                                "data as well (Bayes factor under 20): the structure is "
                                "uncertain"))
        for other in apart:
            gap = penalised(fit) - penalised(other)
            doubts.append(Doubt("two optima",
                          f"d{state}/dt: the structure search from another start ended at "
                          f"{_describe(other, fit, features)} (log Bayes factor "
                          f"{abs(gap):.0f} {'below' if gap >= 0 else 'above'}): the evidence "
                          "has two optima, the structure is uncertain"))
        if choice is not None and not same_structure(choice.fit, fit):
            gap = penalised(choice.fit) - penalised(fit)
            if gap > LOG_PRIOR_ODDS:
                doubts.append(Doubt("preferred structure", f"d{state}/dt: the exact model prefers "
                              f"{_describe(choice.fit, fit, features)} (log Bayes factor "
                              f"{gap:.0f})"))
        doubts += _equation_doubts(i, state, fit, exact, generator_mean, mean, sd, threshold,
                                   features, scale, generator_misfit)
    return Assessment(mean, sd, lower, upper, tuple(doubts))


def _posterior(fit, basis, n_times, n_features):
    """(mean, sd) of every coefficient of one equation, normalised: (T, F) each."""
    m, s = np.zeros((n_times, n_features)), np.zeros((n_times, n_features))
    if not np.isfinite(fit.score):
        return m, s
    series, spread = fit.series(*basis)
    for a, k in enumerate(fit.varying):
        m[:, k], s[:, k] = series[:, a], spread[:, a]
    for j, value, spread in zip(fit.constant, fit.constants, fit.constant_sd(), strict=True):
        m[:, j], s[:, j] = value, spread
    return m, s


def _describe(other, fit, features):
    """How structure ``other`` differs from ``fit``, in words."""
    parts = []
    for j in sorted(set(other.support) - set(fit.support)):
        parts.append(f"with {features[j]}" + (" varying" if j in other.varying else ""))
    for j in sorted(set(fit.support) - set(other.support)):
        parts.append(f"without {features[j]}")
    for j in sorted(set(other.varying) & set(fit.support) - set(fit.varying)):
        parts.append(f"{features[j]} varying")
    for j in sorted(set(fit.varying) & set(other.support) - set(other.varying)):
        parts.append(f"{features[j]} constant")
    return "a structure " + ", ".join(parts) if parts else "another structure"


def _equation_doubts(i, state, fit, exact, generator_mean, mean, sd, threshold, features,
                     scale, generator_misfit):
    out = []
    noise = exact.models[i].noise_variance  # the measurement noise (normalised)
    if np.isfinite(fit.noise_variance) and fit.noise_variance > MISFIT * noise:
        out.append(Doubt("equation misfit", f"d{state}/dt: the fitted equation leaves a misfit of "
                   f"{fit.noise_variance / noise:.0f} times the measurement noise variance: "
                   "a term the library lacks, or a state that is not observed"))
    if generator_misfit is not None and generator_misfit[i] > 10.0:
        out.append(Doubt("generator misfit", f"d{state}/dt: the generator's derivative misfit is "
                   f"{generator_misfit[i]:.0f} times the derivative noise variance"))
    for k in fit.support:
        size = float(np.mean(np.abs(mean[:, i, k]))) / abs(scale[i, k])
        if size < NEAR_THRESHOLD * threshold:
            out.append(Doubt("small term",
                       f"d{state}/dt: {features[k]} explains only {size:.1%} of its equation "
                       f"(threshold {threshold:.0%}): a small change of the threshold "
                       "changes the support"))
    for k in fit.varying:
        gen, ex = generator_mean[:, i, k], mean[:, i, k]
        if np.std(ex) < threshold * abs(scale[i, k]):  # no material variation to compare
            continue
        agree = 1.0 - np.sum((gen - ex) ** 2) / max(float(np.sum((ex - ex.mean()) ** 2)),
                                                      1e-300)
        if agree < AGREE:
            out.append(Doubt("generator disagreement",
                       f"d{state}/dt: the generator's coefficient of {features[k]} disagrees "
                       f"with the exact model's (R^2 {agree:.2f} against it): one of them "
                       "misreads the variation; the band holds both"))
    return out


__all__ = ["Assessment", "EquationChoice", "assess"]
