"""Local polynomial fits on the actual sample times: Savitzky-Golay for any spacing.

A Savitzky-Golay filter is a least-squares polynomial fit over a window of samples,
evaluated at the window's centre; on a uniform grid it reduces to fixed weights. On
irregular times the same fit is done with each window's own times, which is what these
functions do, block by block (memory grows with the block, not the series). Every
estimate is a linear combination of the data, so its white-noise gain (the sum of
squared weights) comes with it.
"""

from __future__ import annotations

import numpy as np

ORDER = 3  # polynomial order of every local fit
_BLOCK = 4096  # samples per block of the batched solves


def is_uniform(t) -> bool:
    """Whether the sample times are equally spaced (to 1e-6 of the step)."""
    steps = np.diff(np.asarray(t, dtype=float))
    return len(steps) == 0 or bool(np.allclose(steps, steps.mean(), rtol=1e-6, atol=0))


def positions(t):
    """Sample times in units of the mean step from the first sample, or None for a
    uniform grid (where they are the sample indices)."""
    t = np.asarray(t, dtype=float)
    if is_uniform(t):
        return None
    return (t - t[0]) / ((t[-1] - t[0]) / (len(t) - 1))


def fit(x, t, window: int, deriv: int, edge: int | None = None):
    """Local polynomial fits of order :data:`ORDER` on ``window`` samples around each
    sample (shifted inwards at the ends), evaluated at that sample.

    Parameters
    ----------
    x : (n, k) data; t : (n,) increasing times
    window : odd number of samples per fit (at most n)
    deriv : 0 for the smoothed value, 1 for the first derivative
    edge : optional smaller odd window used within ``window // 2`` samples of either
        end (less extrapolation bias there)

    Returns
    -------
    values : (n, k)
    gain : (n,) sum of squared weights (white-noise variance gain of each estimate)
    """
    x = np.asarray(x, dtype=float)
    t = np.asarray(t, dtype=float)
    n = len(t)
    half = window // 2
    sizes = np.full(n, window)
    if edge is not None and edge < window:
        sizes[:half] = edge
        sizes[n - half:] = edge
    values = np.empty((n, x.shape[1]))
    gain = np.empty(n)
    for size in np.unique(sizes):
        rows = np.flatnonzero(sizes == size)
        for lo in range(0, len(rows), _BLOCK):
            block = rows[lo:lo + _BLOCK]
            weights, starts = _weights(t, block, int(size), deriv)
            idx = starts[:, None] + np.arange(int(size))[None, :]
            values[block] = np.einsum("bw,bwk->bk", weights, x[idx])
            gain[block] = np.sum(weights**2, axis=1)
    return values, gain


def _weights(t, rows, size, deriv):
    """Weights (len(rows), size) of the fit at each sample of ``rows`` and the first
    sample of each one's window."""
    n = len(t)
    starts = np.clip(rows - size // 2, 0, n - size)
    idx = starts[:, None] + np.arange(size)[None, :]
    span = t[idx[:, -1]] - t[idx[:, 0]]
    u = (t[idx] - t[rows][:, None]) / span[:, None]  # centred and scaled: well conditioned
    order = min(ORDER, size - 1)
    vander = u[..., None] ** np.arange(order + 1)  # (b, size, order + 1)
    gram = np.einsum("bsa,bsc->bac", vander, vander)
    coef = np.linalg.solve(gram, np.swapaxes(vander, 1, 2))  # (b, order + 1, size)
    return coef[:, deriv, :] / span[:, None] ** deriv, starts


def neighbour_residuals(x, t):
    """Each interior sample minus its prediction by the cubic through its two
    neighbours on either side, scaled to unit noise gain: white noise of standard
    deviation s gives residuals of standard deviation s, whatever the spacing. On a
    uniform grid these are the 4th differences over sqrt(70). Returns (n - 4, k)."""
    x = np.asarray(x, dtype=float)
    t = np.asarray(t, dtype=float)
    k = np.arange(2, len(t) - 2)
    others = np.stack([k - 2, k - 1, k + 1, k + 2], axis=1)
    tk = t[k][:, None]
    to = t[others]
    weights = np.ones_like(to)
    for j in range(4):  # Lagrange basis polynomial of neighbour j at t_k
        for m in range(4):
            if m != j:
                weights[:, j] *= (tk[:, 0] - to[:, m]) / (to[:, j] - to[:, m])
    pred = np.einsum("bj,bjk->bk", weights, x[others])
    return (x[k] - pred) / np.sqrt(1.0 + np.sum(weights**2, axis=1))[:, None]
