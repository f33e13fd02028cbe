"""The data side of stage one's varying-coefficient model: B-splines in time and the
normal equations of the integral form.

Each trajectory is cut into consecutive windows; within a window the measured states
are modelled by their integral::

    x(t) = level + integral from the window's start to t of theta(x) xi(t) dt + noise

with a free level per window (profiled out: both sides centred within the window) and
every coefficient series xi_k(t) a cubic B-spline in time (knots equally spaced in
time, whatever the sampling). The noise is the measurement noise itself: independent,
one error per sample, no smoothing bias (a jump of xdot is integrated exactly) and no
correlation from a differentiator. :class:`LevelGram` accumulates the normal equations
for every library column at once, banded in the knot index, so a structure of any
support costs one banded factorisation (:mod:`.vcm_fit`); memory and time grow
linearly with the samples and the knots.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ORDER = 4  # cubic B-splines: four non-zero basis functions at every time
# samples x knots x features held at once when the normal equations are accumulated
# (each (windows, window length, reach, F) array of a block: 32 MB in float64)
_BLOCK = 4_000_000


def spline_basis(times: np.ndarray, n_knots: int, span: tuple[float, float]):
    """Cubic B-splines with ``n_knots`` basis functions equally spaced over ``span``.

    Returns (first, values): the index of the first of the four non-zero basis
    functions at every time (n,) and their values (n, 4), which sum to one.
    """
    t0, t1 = span
    h = (t1 - t0) / max(n_knots - 3, 1)
    u = (np.asarray(times, float) - t0) / h
    first = np.clip(np.floor(u).astype(int), 0, n_knots - ORDER)
    x = u - first
    values = np.stack([(1 - x) ** 3, 3 * x**3 - 6 * x**2 + 4, -3 * x**3 + 3 * x**2 + 3 * x + 1,
                       x**3], axis=1) / 6.0
    return first, values


@dataclass(frozen=True)
class EquationGram:
    """Normal equations of one equation (a view of :class:`WindowGram`)."""

    band: np.ndarray  # (reach, n_knots, F, F): element ((m, j), (m + d, k))
    spline_const: np.ndarray  # (n_knots, F, F): ((m, k), constant j)
    spline_y: np.ndarray  # (n_knots, F)
    const: np.ndarray  # (F, F)
    const_y: np.ndarray  # (F,)
    yy: float
    n: float  # independent observations

    @property
    def n_knots(self):
        return self.band.shape[1]

    @property
    def n_features(self):
        return self.band.shape[2]

    @property
    def reach(self):
        return self.band.shape[0]


class LevelGram:
    """Normal equations of the integral form, shared by all equations.

    Parameters
    ----------
    states : list of (n, S) arrays of the measured states, divided by the derivative
        scale (so that coefficients are in the normalised units of stage one)
    times : list of (n,) arrays
    thetas : list of (n, F) arrays: the normalised library on the measured states
    n_knots : int
    span : (t0, t1), the knots' range (one clock for every trajectory)
    window : int, samples per window
    phi : float
        Correlation of the measurement noise between neighbouring samples (AR(1);
        default 0, white). With ``phi > 0`` (uniform sampling) both sides are whitened
        within each window (generalised least squares: ``z_i - phi z_(i-1)``, scaled
        by ``1 / sqrt(1 - phi^2)``, the window's first sample dropped), so every
        sample's new information counts once (correlation 0.9 between 2000 samples
        leaves about 105 independent ones) and the errors have the noise's marginal
        variance; each window's level stays a constant and is profiled out as before.

    Attributes
    ----------
    n : float
        Independent observations: samples minus one level per window.
    """

    def __init__(self, states, times, thetas, n_knots, span, window, phi=0.0):
        n_features, n_states = thetas[0].shape[1], states[0].shape[1]
        self.n_knots = n_knots
        self.n = 0.0
        plans = []
        for t in times:
            first, values = spline_basis(t, n_knots, span)
            starts = window_starts(len(t), window)
            stops = np.append(starts[1:], len(t))
            plans.append((first, values, starts, stops))
        reach = max(int(np.max(f[stop - 1] - f[st])) for f, _, st, stop in plans) + ORDER
        rows_total = n_knots + reach  # slots past the last knot hold zeros: room, then cut
        self.band = np.zeros((reach, rows_total, n_features, n_features))
        self.spline_const = np.zeros((rows_total, n_features, n_features))
        self.spline_y = np.zeros((rows_total, n_features, n_states))
        self.const = np.zeros((n_features, n_features))
        self.const_y = np.zeros((n_features, n_states))
        self.yy = np.zeros(n_states)
        for x, t, th, (first, values, starts, stops) in zip(states, times, thetas, plans,
                                                           strict=True):
            length = int(np.max(stops - starts))
            per_block = max(1, _BLOCK // (length * reach * n_features))
            for lo in range(0, len(starts), per_block):
                sl = slice(lo, lo + per_block)
                self._add(*_level_integrals(x, t, th, first, values, starts[sl], stops[sl],
                                            reach, float(phi)))
        self.band = self.band[:, :n_knots]
        self.spline_const = self.spline_const[:n_knots]
        self.spline_y = self.spline_y[:n_knots]

    def _add(self, cum, start, y, mask):
        reach, n_features = cum.shape[2], cum.shape[3]
        self.n += float(mask.sum() - mask.shape[0])  # one level per window
        consts = cum.sum(axis=2)  # (W, L, F): B-splines sum to one
        for d in range(reach):
            prod = np.einsum("wilj,wilk->wljk", cum[:, :, : reach - d], cum[:, :, d:])
            rows = (start[:, None] + np.arange(reach - d)).ravel()
            np.add.at(self.band[d], rows, prod.reshape(-1, n_features, n_features))
        rows = (start[:, None] + np.arange(reach)).ravel()
        np.add.at(self.spline_const, rows, np.einsum("wilk,wij->wlkj", cum, consts).reshape(
            -1, n_features, n_features))
        np.add.at(self.spline_y, rows, np.einsum("wilk,wis->wlks", cum, y).reshape(
            -1, n_features, y.shape[2]))
        self.const += np.einsum("wij,wik->jk", consts, consts)
        self.const_y += np.einsum("wij,wis->js", consts, y)
        self.yy += np.einsum("wis,wis->s", y, y)

    def equation(self, i: int) -> EquationGram:
        """The normal equations of equation ``i``."""
        return EquationGram(self.band, self.spline_const, self.spline_y[:, :, i], self.const,
                            self.const_y[:, i], float(self.yy[i]), self.n)


def window_starts(n: int, window: int) -> np.ndarray:
    """First sample of each window: consecutive windows of ``window`` samples (at least
    3), the last one taking the remainder."""
    window = max(3, min(int(window), n))
    return np.arange(0, max(n - window, 0) + 1, window)


def _slopes(values, t, mask):
    """Time derivative of ``values`` (W, L, ...) along axis 1 within each window:
    second-order differences on the actual times (one-sided at the window's ends)."""
    out = np.zeros_like(values)
    count = mask.sum(axis=1).astype(int)
    shape = (-1,) + (1,) * (values.ndim - 2)
    h = np.diff(t, axis=1)
    h0 = h[:, :-1].reshape(*h[:, :-1].shape, *shape[1:])
    h1 = h[:, 1:].reshape(*h[:, 1:].shape, *shape[1:])
    v0, v1, v2 = values[:, :-2], values[:, 1:-1], values[:, 2:]
    out[:, 1:-1] = (h0**2 * (v2 - v1) + h1**2 * (v1 - v0)) / (h0 * h1 * (h0 + h1))
    out[:, 0] = (values[:, 1] - values[:, 0]) / h[:, 0].reshape(shape)
    rows = np.arange(values.shape[0])
    last = np.maximum(count - 1, 1)
    hl = (t[rows, last] - t[rows, last - 1]).reshape(shape)
    out[rows, last] = (values[rows, last] - values[rows, last - 1]) / hl
    return out * mask.reshape(*mask.shape, *shape[1:])


def _uniform_windows(step):
    """Whether each window's steps (W, L - 1; padding 0) are equal (to 1e-6)."""
    used = step > 0
    mean = step.sum(axis=1) / np.maximum(used.sum(axis=1), 1)
    return np.all(~used | (np.abs(step - mean[:, None]) <= 1e-6 * mean[:, None]), axis=1)


def _level_integrals(x, t, theta, first, values, starts, stops, reach, phi=0.0):
    """Centred cumulative integrals of theta_k B_m within some windows of a trajectory
    (whitened for AR(1) noise of correlation ``phi``: see :class:`LevelGram`).

    Returns (cum (W, L, reach, F) against knots start + l, start knot of each window
    (W,), centred states (W, L, S), mask (W, L)): window w holds samples
    starts[w] .. stops[w] - 1, padded to the longest window (``mask`` 0)."""
    n = len(t)
    length = int(np.max(stops - starts))
    idx = starts[:, None] + np.arange(length)
    mask = (idx < stops[:, None]).astype(float)
    idx = np.minimum(idx, n - 1)
    start = first[starts]
    n_w = len(starts)
    # point values theta_k(t) B_(start + l)(t) on every sample of every window
    point = np.zeros((n_w, length, reach, theta.shape[1]))
    wi = np.repeat(np.arange(n_w), length)
    ii = np.tile(np.arange(length), n_w)
    for a in range(ORDER):
        slot = np.where(mask > 0, first[idx] + a - start[:, None], 0).ravel()
        point[wi, ii, slot] += (values[idx, a] * mask).reshape(-1, 1) * theta[idx.ravel()]
    # cumulative integral from the window's first sample: the trapezoid rule with its
    # end correction (Euler-Maclaurin), fourth order; plain trapezoids bias Lorenz's
    # coefficients by about 0.5% at 100 samples per time unit. The correction
    # telescopes only where the steps are equal: on irregular times each interval's
    # h^2 / 12 differs, so the slopes' noise (from steps that can be tiny) stays in
    # every interval and swamps the integral; a window whose steps are not uniform
    # (random or jittered times, a gap, a change of rate) uses the plain rule
    tt = t[idx] + (1 - mask) * (np.arange(length)[None, :] + 1.0)  # padding: unit steps
    step = np.diff(tt, axis=1) * mask[:, 1:]
    slope = _slopes(point, tt, mask)
    correction = step[..., None, None] / 12.0 * (slope[:, 1:] - slope[:, :-1])
    area = 0.5 * (point[:, 1:] + point[:, :-1]) - _uniform_windows(step)[:, None, None,
                                                                         None] * correction
    cum = np.zeros_like(point)
    cum[:, 1:] = np.cumsum(step[..., None, None] * area, axis=1)
    y = x[idx] * mask[..., None]
    if phi > 0:
        mask = _whitened(mask, 0.0)
        cum = _whitened(cum, phi) * mask[..., None, None]
        y = _whitened(y, phi) * mask[..., None]
    # profile out each window's level: centre over its samples
    count = mask.sum(axis=1)
    cum = (cum - (cum * mask[..., None, None]).sum(axis=1, keepdims=True)
           / count[:, None, None, None]) * mask[..., None, None]
    y = (y - y.sum(axis=1, keepdims=True) / count[:, None, None]) * mask[..., None]
    return cum, start, y, mask


def _whitened(values, phi):
    """``values`` (W, L, ...) whitened along each window's samples for AR(1) noise of
    correlation ``phi``: ``(z_i - phi z_(i-1)) / sqrt(1 - phi^2)``, the first sample
    dropped (zero; for ``phi = 0`` only that). A window's level ``c`` becomes
    ``c sqrt((1 - phi) / (1 + phi))`` on every remaining sample: still a constant."""
    out = np.zeros_like(values)
    out[:, 1:] = (values[:, 1:] - phi * values[:, :-1]) / np.sqrt(1.0 - phi**2)
    return out
