"""Noise that follows the signal: counts (Poisson) and multiplicative noise.

The noise level that is the unit of every misfit and held-out score is a robust
(median) statistic of high-order differences. Where the noise's spread grows with the
signal's level, as counts' does (variance proportional to the mean) or multiplicative
noise's, the median is that of the quieter samples, and a right law's held-out score
reads the ratio of the mean noise variance to it (Poisson counts of an epidemic wave:
1.7-2.4 where the law was exact). The fits keep that unit (raising it to the mean
changed which laws the search found); what changes is the reference a score is read
against: :mod:`latentsindy._stage_two.fit.expected_score` simulates noise of this
shape (:func:`level_profile`).

The shape is measured where it is plain: dense samples, the noise's spread in bins of
the signal's level (each robust on its own: isolated spikes do not count) rising with
the level, the 4th and 6th differences agreeing in every bin (white noise reads the
same at every order; a sharp feature of the signal, such as a neuron's spike at its
highest level, does not, and is not noise), and the mean variance of a power law of
the level through the bins (counts: a square root) above the median's by ``PLAIN``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

BINS = 6  # bins of the signal's level
MIN_PER_BIN = 64  # samples per bin at least: below that no shape is measured
AGREE = 0.2  # 4th and 6th differences' levels within this fraction in every bin
RISES = 0.8  # rank correlation between the bins' level and noise spread at least
PLAIN = 1.1  # RMS over median level from here; white noise reads 1.00-1.03
_MAD_EFFICIENCY = 1.36  # variance of a MAD estimate of sigma: 1.36 sigma^2 / n


def level_factor(x) -> np.ndarray:
    """Per column of ``x`` (one recording on a uniform grid, or a list of them): the
    root-mean-square noise level over the median one; 1 where the noise does not
    plainly follow the signal."""
    xs = _pieces(x)
    return np.array([float(np.sqrt(np.mean(np.concatenate(
        [p[:, j] for p in level_profile(xs)]) ** 2))) for j in range(xs[0].shape[1])])


def level_profile(x) -> list[np.ndarray]:
    """Per recording, the noise's spread at every sample in units of the median level
    (an array like the recording's); ones where the noise does not plainly follow the
    signal."""
    xs = _pieces(x)
    out = [np.ones_like(xk) for xk in xs]
    long = [xk for xk in xs if len(xk) > 14]
    if not long or sum(len(xk) - 6 for xk in long) < BINS * MIN_PER_BIN:
        return out
    d4 = np.vstack([np.diff(xk, 4, axis=0)[1:-1] / math.sqrt(70.0) for xk in long])
    d6 = np.vstack([np.diff(xk, 6, axis=0) / math.sqrt(924.0) for xk in long])
    level = np.vstack([xk[3:-3] for xk in long])
    for j in range(xs[0].shape[1]):
        law = _power_law(level[:, j], d4[:, j], d6[:, j])
        if law is None:
            continue
        spread = law(level[:, j])
        if math.sqrt(np.mean(spread**2)) <= PLAIN:
            continue
        for k, xk in enumerate(xs):
            out[k][:, j] = law(xk[:, j])
    return out


def _pieces(x) -> list[np.ndarray]:
    return [np.asarray(xk, float).reshape(len(xk), -1)
            for xk in (x if isinstance(x, list | tuple) else [x])]


def _power_law(level, d4, d6):
    """The noise's spread as a function of the level, in units of the pooled median
    level (``spread = a level^p`` through the bins), or None where it is not plain."""
    edges = np.quantile(level, np.linspace(0, 1, BINS + 1))
    which = np.clip(np.searchsorted(edges, level, side="right") - 1, 0, BINS - 1)
    spread4, spread6, mid = [], [], []
    for b in range(BINS):
        inside = which == b
        if inside.sum() < MIN_PER_BIN:
            return None
        spread4.append(_mad(d4[inside]))
        spread6.append(_mad(d6[inside]))
        mid.append(float(np.median(level[inside])))
    spread4, spread6, mid = np.array(spread4), np.array(spread6), np.array(mid)
    pooled = _mad(d4)
    positive = (mid > 0) & (spread4 > 0)
    if (pooled <= 0 or np.any(spread6 <= 0) or positive.sum() < 3
            or np.any(np.abs(spread4 / spread6 - 1) > AGREE)
            or np.ptp(spread4) == 0 or np.ptp(mid) == 0  # no rank correlation to read
            or not stats.spearmanr(mid, spread4).statistic >= RISES):
        return None
    p, log_a = np.polyfit(np.log(mid[positive]), np.log(spread4[positive]), 1)
    floor = mid[positive][0] / 10
    # a bin's MAD reads sigma^2 (1 + 1.36 / n) on average: taken out
    unbiased = math.exp(log_a) / math.sqrt(1 + _MAD_EFFICIENCY * BINS / len(level))
    return lambda v: unbiased * np.maximum(np.asarray(v, float), floor) ** p / pooled


def _mad(d) -> float:
    return float(1.4826 * np.median(np.abs(d - np.median(d))))
