"""Turning an inferred input u(t) into a two-level switch.

:func:`two_level_switch` is the principled segmentation: the two levels and the
labels minimise ``sum_t (u_t - level[s_t])^2 + penalty * (number of switches)``, found
by alternating the level means with an exact dynamic programme over the labels
(Viterbi on a two-state chain). The default penalty follows the Bayesian information
criterion: a switch adds one parameter (its time), which BIC charges ``sigma^2 log(n)``
in squared-error units (``sigma^2``: the variance of u around its nearest level). We
charge twice that, because an inferred u is smoothed and autocorrelated, so it holds
fewer independent samples than n and BIC's charge would admit spurious short switches.
:func:`sigmoid_switch` is the seed paper's recipe, kept for comparison.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_MAX_ROUNDS = 50


@dataclass(frozen=True)
class Switch:
    """A two-level piecewise-constant signal.

    Attributes
    ----------
    times : ndarray (n_times,)
        Sample times.
    labels : ndarray of int (n_times,)
        0 where the signal is at its low level, 1 at its high level.
    levels : ndarray (2,)
        Low and high level.
    penalty : float
        Cost of one switch used by the segmentation (squared-error units).
    """

    times: np.ndarray = field(repr=False)
    labels: np.ndarray = field(repr=False)
    levels: np.ndarray
    penalty: float

    @property
    def values(self) -> np.ndarray:
        """The switch signal at the sample times."""
        return self.levels[self.labels]

    @property
    def switch_times(self) -> np.ndarray:
        """Times at which the level changes (midpoints between samples)."""
        i = np.flatnonzero(np.diff(self.labels))
        return 0.5 * (self.times[i] + self.times[i + 1])

    def at(self, t) -> np.ndarray:
        """The switch signal at arbitrary times (the level of the nearest sample before)."""
        idx = np.searchsorted(self.times, np.asarray(t, dtype=float), side="right") - 1
        return self.levels[self.labels[np.clip(idx, 0, self.times.size - 1)]]


def two_level_switch(u, t, *, penalty: float | None = None) -> Switch:
    """Segment a series into two levels with as few switches as the data support.

    Parameters
    ----------
    u : array (n_times,)
        The series, e.g. the inferred input of a dynamic SINDy fit.
    t : array (n_times,)
        Its sample times (increasing).
    penalty : float, optional
        Cost of one switch in squared-error units; default ``2 sigma^2 log(n)`` (twice
        BIC's charge for one parameter; see the module notes).

    Returns
    -------
    Switch

    Examples
    --------
    >>> import numpy as np
    >>> t = np.arange(200.0)
    >>> u = np.where((t > 50) & (t < 120), 1.0, -1.0) + 0.1 * np.sin(t)
    >>> two_level_switch(u, t).switch_times
    array([ 50.5, 119.5])
    """
    u = np.asarray(u, dtype=float)
    t = np.asarray(t, dtype=float)
    if u.ndim != 1 or u.shape != t.shape or u.size < 4:
        raise ValueError(f"u and t must be 1-D arrays of the same length >= 4; got shapes "
                         f"{u.shape} and {t.shape}.")
    if not np.all(np.isfinite(u)):
        raise ValueError("u contains NaN or inf; interpolate or drop those samples first.")
    if penalty is not None and not penalty >= 0:
        raise ValueError(f"penalty must be >= 0; got {penalty}.")
    levels = np.quantile(u, [0.1, 0.9])
    if levels[1] - levels[0] <= 1e-12 * max(1.0, float(np.abs(u).max())):
        return Switch(t, np.zeros(u.size, dtype=int), np.array([u.mean(), u.mean()]),
                      float(penalty or 0.0))
    labels = _nearest(u, levels)
    for _ in range(_MAX_ROUNDS):  # two-means: levels without a switch penalty
        new = _means(u, labels, levels)
        labels = _nearest(u, new)
        if np.allclose(new, levels):
            break
        levels = new
    if penalty is None:
        sigma2 = float(np.mean((u - levels[labels]) ** 2))
        penalty = 2.0 * sigma2 * np.log(u.size)
    for _ in range(_MAX_ROUNDS):
        labels = _viterbi(u, levels, penalty)
        new = _means(u, labels, levels)
        if np.allclose(new, levels):
            break
        levels = new
    if levels[0] > levels[1]:
        levels, labels = levels[::-1].copy(), 1 - labels
    return Switch(t, labels, levels, float(penalty))


def sigmoid_switch(u, *, steepness: float = 1000.0) -> np.ndarray:
    """The seed paper's switch (supplement 3.2): centre u, squash it with a steep
    sigmoid, rescale to u's centred range and add the mean back.

    ``steepness`` multiplies u in u's own units, so the result depends on them; prefer
    :func:`two_level_switch`.
    """
    u = np.asarray(u, dtype=float)
    mean = u.mean()
    centred = u - mean
    lo, hi = centred.min(), centred.max()
    squashed = 0.5 * (1.0 + np.tanh(0.5 * steepness * centred))  # overflow-free sigmoid
    return lo + (hi - lo) * squashed + mean


def _nearest(u, levels):
    return (np.abs(u - levels[1]) < np.abs(u - levels[0])).astype(int)


def _means(u, labels, previous):
    out = previous.copy()
    for k in (0, 1):
        if np.any(labels == k):
            out[k] = u[labels == k].mean()
    return out


def _viterbi(u, levels, penalty):
    """Exact minimiser of squared error plus ``penalty`` per switch over 0/1 labels."""
    n = u.size
    cost = (u[:, None] - levels[None, :]) ** 2
    total = cost[0].copy()
    came_from_other = np.zeros((n, 2), dtype=bool)
    for i in range(1, n):
        switched = total[::-1] + penalty
        came_from_other[i] = switched < total
        total = np.minimum(total, switched) + cost[i]
    labels = np.empty(n, dtype=int)
    labels[-1] = int(np.argmin(total))
    for i in range(n - 1, 0, -1):
        labels[i - 1] = 1 - labels[i] if came_from_other[i, labels[i]] else labels[i]
    return labels
