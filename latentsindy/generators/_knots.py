"""The uniform knot grid of a piecewise-linear series read at its samples (timeVAE):
where each sample sits between two knots, and the samples' differences as fixed
combinations of the knots' differences ``d_k = x_{k+1} - x_k`` (used by
``_stage_one/knot_loss.py``). Everything is O(samples): no (samples x knots) matrix is
formed."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sparse

EXACT_ZERO = 1e-9  # a combination weight below this is a zero that rounded


def knot_grid(n_times: int, n_knots: int):
    """Left knot and fraction of every sample on the uniform grid (as
    ``F.interpolate(..., align_corners=True)``); ``(left, frac)``."""
    where = np.arange(n_times, dtype=np.float64) * ((n_knots - 1) / max(n_times - 1, 1))
    left = np.clip(np.floor(where).astype(np.int64), 0, n_knots - 2)
    return left, where - left


def interpolation(left, frac, n_knots):
    """Sparse float32 matrices of the linear read-out: (T, K) knots -> samples, and its
    transpose (K, T) (samples' gradients -> knots)."""
    n_times = len(left)
    frac = np.asarray(frac, dtype=np.float32)
    rows = np.repeat(np.arange(n_times), 2)
    cols = np.stack([left, left + 1], axis=1).ravel()
    vals = np.stack([1 - frac, frac], axis=1).ravel()
    matrix = sparse.csr_matrix((vals, (rows, cols)), shape=(n_times, n_knots), dtype=np.float32)
    return matrix, matrix.T.tocsr()


def applies(n_times: int, n_knots: int, uniform: bool) -> bool:
    """Whether the samples' differences have the form below: a uniform grid with at
    least two samples per knot interval (no sample step spans a whole interval)."""
    return uniform and n_knots >= 3 and (n_times - 1) >= 2 * (n_knots - 1)


def step_pairs(left, frac):
    """Each sample step ``x(t + 1) - x(t)`` as ``w1 d_{c1} + w2 d_{c2}``: inside one
    interval ``c1 = c2`` and ``w2 = 0``; across knot ``c2 = c1 + 1``, the two shares.
    Returns ``(c1, w1, c2, w2)``, weights in float64 (a zero share is 0)."""
    same = left[1:] == left[:-1]
    c1, c2 = left[:-1].copy(), left[1:].copy()
    w1 = np.where(same, frac[1:] - frac[:-1], 1.0 - frac[:-1])
    w2 = np.where(same, 0.0, frac[1:])
    w1[np.abs(w1) < EXACT_ZERO] = 0.0
    w2[np.abs(w2) < EXACT_ZERO] = 0.0
    return c1, w1, c2, w2


def curve_rows(left, frac, n_knots):
    """The samples' second differences that can bend, each as ``a d_{k-1} + b d_k`` at
    an interior knot ``k`` (1 .. K - 2); the others are zero in exact arithmetic.
    Returns ``(rows, k, a, b)``: their indices among the ``n_times - 2`` and the knot
    and weights of each (float64)."""
    c1, w1, c2, w2 = step_pairs(left, frac)
    # row r: step r + 1 minus step r, four (column, weight) pairs over two columns
    cols = np.stack([c1[1:], c2[1:], c1[:-1], c2[:-1]], axis=1)
    weights = np.stack([w1[1:], w2[1:], -w1[:-1], -w2[:-1]], axis=1)
    high = cols.max(axis=1)
    if np.any(high - cols.min(axis=1) > 1):
        raise ValueError("curve_rows needs at least two samples per knot interval.")
    on_high = np.where(cols == high[:, None], weights, 0.0).sum(axis=1)
    on_low = np.where(cols != high[:, None], weights, 0.0).sum(axis=1)
    on_high[np.abs(on_high) < EXACT_ZERO] = 0.0
    on_low[np.abs(on_low) < EXACT_ZERO] = 0.0
    rows = np.flatnonzero((on_high != 0) | (on_low != 0))
    # a row that reads one interval only is written at its right end's knot where
    # there is one (d_{k-1} with k = c + 1), else at its left end's (d_k, k = c)
    k = high[rows].copy()
    a, b = on_low[rows].copy(), on_high[rows].copy()
    alone = a == 0
    shift = alone & (k + 1 <= n_knots - 2)
    k[shift] += 1
    a[shift], b[shift] = b[shift], 0.0
    if np.any((k < 1) | (k > n_knots - 2)):
        raise ValueError("curve_rows: a second difference outside the interior knots.")
    return rows, k, a, b
