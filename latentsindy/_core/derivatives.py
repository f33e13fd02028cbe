"""Time derivatives that are robust to measurement noise by default.

The default, :class:`AdaptiveSavitzkyGolay`, estimates each state's noise level from
high-order differences and picks, per state, the widest Savitzky-Golay window whose
residual stays within that noise level (Morozov's discrepancy principle). On clean
data this falls back to a short window (high accuracy); on noisy data the window
grows with the noise. Irregular sample times get the same fits on their actual times
(:mod:`.local_fits`), never a grid they do not have. Any pysindy differentiation
object can be passed instead.
"""

from __future__ import annotations

import math

import numpy as np
import pysindy as ps
from scipy.signal import savgol_coeffs, savgol_filter

from . import local_fits
from .coloured import ar1_gain, with_ar1
from .local_fits import ORDER as _POLYORDER


def noise_level(x, t=None) -> np.ndarray:
    """Robust per-column noise standard deviation (MAD) of white measurement noise.

    On a uniform grid (or without ``t``) from 4th differences; on irregular times from
    each sample's residual against the cubic through its neighbours, scaled by that
    prediction's own noise gain (the same statistic, for any spacing). ``x`` may be a
    list of trajectories with ``t`` a list of their times: their residuals are pooled,
    so every sample counts once (a mean of per-trajectory levels would let a short
    segment's rough estimate weigh as much as a long one's)."""
    if isinstance(x, list | tuple):
        times = [None] * len(x) if t is None else list(t)
        if len(x) == 1:
            return noise_level(x[0], times[0])
        d = np.vstack([_noise_residuals(np.asarray(xk, float), tk)
                       for xk, tk in zip(x, times, strict=True)])
        return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    if _irregular(t):
        d = local_fits.neighbour_residuals(x, t)
        return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    d = np.diff(x, n=4, axis=0)
    mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(70.0)  # var of 4th difference of white noise = 70 sigma^2


# Difference orders :func:`measurement_noise` compares, and the share below the 4th
# order's estimate at which a higher order is believed instead (white noise gives the
# same level at every order, within 10% on 60 samples).
_ORDERS = (4, 6, 8, 10)
_DROP = 0.7


def measurement_noise(x, t=None) -> np.ndarray:
    """:func:`noise_level`, with higher-order differences where the samples are few per
    oscillation (uniform grids).

    The 4th difference of a signal sampled ``m`` times per cycle keeps about
    ``(2 pi / m)**4 / sqrt(70)`` of its amplitude: at 12 samples per cycle that is as
    large as 1% noise (prey-only Lotka-Volterra: 0.31 estimated for 0.14 true), and the
    noise level, the unit of every misfit and score, is then overestimated. The k-th
    difference keeps ``(2 pi / m)**k / sqrt(C(2k, k))``, which shrinks with ``k`` above
    about 3 samples per cycle, while white noise reads the same at every order. Where a
    higher order reads below ``_DROP`` times the 4th, the signal shows in the 4th
    and the lowest reading is taken (0.15 at 12 samples per cycle); on densely sampled
    data every order agrees and the 4th is kept. Irregular times and lists of
    recordings as in :func:`noise_level`."""
    if isinstance(x, list | tuple):
        times = [None] * len(x) if t is None else list(t)
        if len(x) == 1:
            return measurement_noise(x[0], times[0])
        if any(_irregular(tk) for tk in times):
            return noise_level(x, t)
        levels = [_by_orders(np.asarray(xk, float)) for xk in x]
        counts = np.array([len(xk) for xk in x], float)
        base = noise_level(x, t)
        ratio = np.sum([c * lv / np.maximum(noise_level(xk), 1e-300)
                        for c, lv, xk in zip(counts, levels, x, strict=True)], axis=0)
        return base * ratio / counts.sum()
    if _irregular(t):
        return noise_level(x, t)
    return _by_orders(np.asarray(x, float))


def state_noise(x, t=None) -> tuple[np.ndarray, np.ndarray]:
    """Per column: ``(sigma, phi)``, the measurement noise's standard deviation and its
    correlation between neighbouring samples: AR(1) where the noise reads as coloured
    (:func:`.coloured.ar1_noise`: its marginal level, which differences of neighbouring
    samples read several times too low), otherwise :func:`noise_level` and ``phi = 0``.
    Lists of recordings are pooled, as in :func:`noise_level`."""
    return with_ar1(noise_level(x, t), x, t)


def marginal_noise(x, t=None) -> np.ndarray:
    """:func:`measurement_noise`, with AR(1) noise's marginal level where the noise
    reads as correlated in time (:func:`.coloured.ar1_noise`)."""
    return with_ar1(measurement_noise(x, t), x, t)[0]


def _by_orders(x):
    """Per column: the 4th-difference level, or the lowest higher-order one where it
    reads below ``_DROP`` times that."""
    levels = []
    for k in _ORDERS:
        if len(x) <= k + 8:
            break
        d = np.diff(x, n=k, axis=0)
        mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0)
        levels.append(1.4826 * mad / np.sqrt(math.comb(2 * k, k)))
    if not levels:
        return noise_level(x)
    levels = np.array(levels)
    low = levels.min(axis=0)
    return np.where(low < _DROP * levels[0], low, levels[0])


def _irregular(t):
    return t is not None and np.ndim(t) > 0 and not local_fits.is_uniform(t)


def _noise_residuals(x, t):
    """Residuals whose standard deviation is that of the white noise in ``x``."""
    if _irregular(t):
        return local_fits.neighbour_residuals(x, t)
    return np.diff(x, n=4, axis=0) / np.sqrt(70.0)


def _max_window(n, max_window):
    return max_window or max(7, min(n // 5, 301))


def _next_window(w):
    return w + 2 if w < 21 else int(w * 1.2) | 1


def window_capped(window: int, n: int, max_window: int | None = None) -> bool:
    """Whether :func:`choose_window` stopped at its largest allowed window for a series
    of ``n`` samples: the series' length, not its noise, limited the window."""
    return _next_window(int(window)) > min(_max_window(n, max_window), n - (1 - n % 2))


def choose_window(x: np.ndarray, max_window: int | None = None, t=None,
                  sigma: float | None = None) -> int:
    """Widest odd window whose smoothing residual stays within the noise level
    ``sigma`` (estimated from ``x`` when not given; fits on the actual times when ``t``
    is irregular)."""
    n = x.shape[0]
    max_window = _max_window(n, max_window)
    irregular = t is not None and not local_fits.is_uniform(t)
    if sigma is None:
        sigma = float(noise_level(x[:, None], t)[0])
    best = _POLYORDER + 2
    if sigma <= 1e-12 * max(1.0, float(np.std(x))):
        return best
    w = best
    while w <= min(max_window, n - (1 - n % 2)):
        if irregular:
            smooth = local_fits.fit(x[:, None], t, w, 0)[0][:, 0]
        else:
            smooth = savgol_filter(x, w, _POLYORDER)
        if np.sqrt(np.mean((x - smooth) ** 2)) > sigma:
            break
        best = w
        w = _next_window(w)
    return best


def _savgol_derivative(x, window, dt):
    """Savitzky-Golay derivative along axis 0; within half a window of either end a
    half-width window is used, which cuts the polynomial-extrapolation bias there."""
    out = savgol_filter(x, window, _POLYORDER, deriv=1, delta=dt, axis=0, mode="interp")
    edge = _edge_window(window)
    if edge < window and x.shape[0] >= window:
        half = window // 2
        head = savgol_filter(x[:window], edge, _POLYORDER, deriv=1, delta=dt, axis=0,
                             mode="interp")
        tail = savgol_filter(x[-window:], edge, _POLYORDER, deriv=1, delta=dt, axis=0,
                             mode="interp")
        out[:half] = head[:half]
        out[-half:] = tail[-half:]
    return out


def _edge_window(window):
    return max(_POLYORDER + 2, (window // 2) | 1)


def _edge_profile(n, window, dt):
    """Per-sample white-noise gain of :func:`_savgol_derivative` (larger at the edges).

    The first ``window`` outputs see the first ``window + window // 2`` samples only
    (the tail's edge fit, ``window // 2`` from the end, stays clear of them), so the
    impulses are differentiated as a series of ``k + window`` samples, not ``n``: the
    same numbers (20,000 samples, window 81: 0.13 -> 0.006 s)."""
    k = min(n, 2 * window)
    impulses = np.zeros((min(n, k + window), k))
    impulses[np.arange(k), np.arange(k)] = 1.0
    head = np.sum(_savgol_derivative(impulses, window, dt)[:window] ** 2, axis=1)
    interior = np.sum(savgol_coeffs(window, _POLYORDER, deriv=1, delta=dt) ** 2)
    gain = np.full(n, interior)
    gain[:window] = np.maximum(head, interior)
    gain[n - window:] = np.maximum(gain[n - window:], head[::-1][-min(window, n):])
    return gain


class AdaptiveSavitzkyGolay(ps.BaseDifferentiation):
    """Savitzky-Golay derivative with a per-state window chosen from the noise level.

    On irregular sample times the same local cubic fits are made on the actual times
    (each window its own least-squares fit), the noise level comes from residuals
    that do not assume a grid, and each sample's derivative carries its own noise gain
    (larger where samples are sparse), which weights the likelihood downstream.

    Parameters
    ----------
    max_window : int, optional
        Upper bound on the window (default: a fifth of the series, at most 301).
    noise_std : float or array (n_states,), optional
        The measurement noise's standard deviation per state, when known (or pooled
        over several recordings of one instrument: a short series estimates its own
        noise level poorly, and an underestimate shrinks the window several-fold).
        Default: estimated from each series (:func:`state_noise`: AR(1) noise's
        marginal level where the noise reads as correlated in time, the white level
        of :func:`noise_level` otherwise).
    noise_correlation : float or array (n_states,), optional
        The noise's correlation between neighbouring samples (AR(1)), used for the
        derivative's noise gain on a uniform grid. Default: estimated with the level
        when ``noise_std`` is not given, otherwise 0 (white).

    Examples
    --------
    >>> import numpy as np
    >>> t = np.linspace(0, 2 * np.pi, 400)
    >>> d = AdaptiveSavitzkyGolay()(np.sin(t)[:, None], t)
    >>> bool(np.max(np.abs(d[:, 0] - np.cos(t))) < 1e-4)
    True
    >>> t = np.sort(np.random.default_rng(0).uniform(0, 2 * np.pi, 400))
    >>> d = AdaptiveSavitzkyGolay()(np.sin(t)[:, None], t)
    >>> bool(np.max(np.abs(d[:, 0] - np.cos(t))) < 1e-3)
    True
    """

    def __init__(self, max_window: int | None = None, noise_std=None,
                 noise_correlation=None):
        self.max_window = max_window
        self.noise_std = noise_std
        self.noise_correlation = noise_correlation

    def _sigmas(self, n_states):
        """The given noise level per state (None entries: estimate)."""
        if self.noise_std is None:
            return [None] * n_states
        return list(_per_state(self.noise_std, n_states, "noise_std",
                                    "non-negative finite number"))

    def _noise(self, x, t):
        """Per state (sigma list, phi array): given, or read from ``x``."""
        n_states = x.shape[1]
        if self.noise_std is None:
            sigma, phi = state_noise(x, t)
            sigma = list(sigma)
        else:
            sigma, phi = self._sigmas(n_states), np.zeros(n_states)
        if self.noise_correlation is not None:
            phi = _per_state(self.noise_correlation, n_states, "noise_correlation",
                             "number in [0, 1)", 1.0)
        self.noise_correlation_ = np.asarray(phi, float)
        return sigma, self.noise_correlation_

    def _differentiate(self, x, t):
        return self._rates(x, t, diagnostics=True)

    def _rates(self, x, t, diagnostics):
        """The derivative of ``x`` and ``windows_``; with ``diagnostics`` also
        ``smoothed_x_``, ``noise_gain_`` and ``noise_profile_`` (as long again to make
        on a grid: :func:`rate` leaves them out)."""
        x = np.asarray(x, dtype=float)
        if np.ndim(t) == 0:
            steps = np.full(x.shape[0] - 1, float(t))
        else:
            steps = np.diff(np.asarray(t, dtype=float))
        if not np.allclose(steps, steps.mean(), rtol=1e-6, atol=0):
            return self._irregular(x, np.concatenate([[0.0], np.cumsum(steps)]),
                                   diagnostics)
        sigmas, phi = self._noise(x, None)
        self.windows_ = [choose_window(x[:, j], self.max_window, sigma=s)
                         for j, s in enumerate(sigmas)]
        smooth = np.empty_like(x)
        out = np.empty_like(x)
        dt = float(steps.mean())
        for j, w in enumerate(self.windows_):
            w = min(w, x.shape[0] - (1 - x.shape[0] % 2))
            if diagnostics:
                smooth[:, j] = savgol_filter(x[:, j], w, _POLYORDER, mode="interp")
            out[:, j] = _savgol_derivative(x[:, j], w, dt)
        if not diagnostics:
            return out
        self.smoothed_x_ = smooth
        coeffs = [savgol_coeffs(w, _POLYORDER, deriv=1, delta=dt) for w in self.windows_]
        self.noise_gain_ = np.array([ar1_gain(c, float(p))
                                     for c, p in zip(coeffs, phi, strict=True)])
        self.noise_profile_ = np.ones_like(x)
        for j, w in enumerate(self.windows_):  # the white gain's shape along the series
            self.noise_profile_[:, j] = (_edge_profile(x.shape[0], w, dt)
                                         / np.sum(coeffs[j] ** 2))
        return out

    def _irregular(self, x, t, diagnostics=True):
        """Local cubic fits on the actual times: windows by the discrepancy principle,
        half-width windows within half a window of the ends (as on a grid)."""
        sigmas, _ = self._noise(x, t)  # irregular times read as white
        self.windows_ = [choose_window(x[:, j], self.max_window, t, s)
                         for j, s in enumerate(sigmas)]
        smooth = np.empty_like(x)
        out = np.empty_like(x)
        gains = np.empty_like(x)
        for j, w in enumerate(self.windows_):
            w = min(w, x.shape[0] - (1 - x.shape[0] % 2))
            if diagnostics:
                smooth[:, j] = local_fits.fit(x[:, j:j + 1], t, w, 0)[0][:, 0]
            deriv, gains[:, j] = local_fits.fit(x[:, j:j + 1], t, w, 1, _edge_window(w))
            out[:, j] = deriv[:, 0]
        if not diagnostics:
            return out
        self.smoothed_x_ = smooth
        # the typical (median) gain plays the role of the grid's interior gain; each
        # sample's own gain relative to it is its noise profile
        self.noise_gain_ = np.median(gains, axis=0)
        self.noise_profile_ = gains / self.noise_gain_
        return out


def _per_state(value, n_states, name, what, high=np.inf) -> np.ndarray:
    """``value`` (one number or one per state) as an (n_states,) array in [0, high)."""
    arr = np.asarray(value, dtype=float)
    if arr.ndim == 0:
        arr = np.full(n_states, float(arr))
    if arr.shape != (n_states,) or not np.all(np.isfinite(arr) & (arr >= 0) & (arr < high)):
        raise ValueError(f"{name} must be one {what} or one per state ({n_states}); got "
                         f"{value!r}.")
    return arr


def rate(x, t):
    """:class:`AdaptiveSavitzkyGolay`'s derivative of ``x`` (T, n) at times ``t`` and
    its windows, without the noise diagnostics it also makes (the smoothed states, the
    noise gain and its profile along the series: on a grid, as long again as the
    derivative): for a derivative that is only used as a series."""
    method = AdaptiveSavitzkyGolay()
    return method._rates(x, t, diagnostics=False), method.windows_


def default_differentiation():
    return AdaptiveSavitzkyGolay()
