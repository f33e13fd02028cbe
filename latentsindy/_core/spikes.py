"""Isolated spikes: single samples far off their neighbours' curve (a loose connector,
a transmission error), found and discounted before anything is fitted.

Every sample is predicted by the cubic through its two neighbours on either side (on
the actual times) and its residual is scaled by that prediction's noise gain, so white
noise gives residuals of one robust spread ``s`` everywhere. A sample is a spike when

* its residual exceeds :data:`Z` times ``s``, read over the :data:`WINDOW` samples
  around it (white noise: 6e-7 of samples; noise whose level follows the signal, as
  counts' does, is judged at its level there),
* the four samples on either side of it lie on one cubic (least squares, within half
  that threshold) and it is off that cubic beyond the threshold, and
* with it replaced by that cubic, the residuals from two samples before to two after
  fall below half the threshold: the rest of the curve is smooth there. A sharp
  feature of the dynamics (a neuron's spike, a relaxation jump) spans several samples
  and leaves its neighbours off the curve too, so it is kept.

Two spikes up to four samples apart hide each other (each one's prediction holds the
other; the sample between two same-signed ones looks like a dip), so where no single
sample passes, pairs around it are tried by the same test; two adjacent samples off
to the same side are a feature two samples wide and are kept. Three spikes within a
few samples are left as they are.

The spread ``s`` is read again after a first pass (a share of spikes inflates it). A
discounted sample takes the cubic's value; :class:`.recordings.DataUse` lists each
one, so nothing is dropped without a word. Data that are already smooth to rounding
(no noise) are left alone: no residual under :data:`FLOOR` of a state's spread is a
spike.
"""

from __future__ import annotations

import numpy as np

Z = 5.0  # residual threshold, in robust spreads of white-noise residuals
PASSES = 2  # passes (the spread read again after each)
WINDOW = 101  # samples over which the residuals' local spread is read
LOCAL = 1.5  # a local spread this many times the whole series' is the noise's own level
# No residual below this share of the state's std is a spike: on exact data the residuals
# are the interpolation's own error (random times: up to 2e-6 of the std), not noise
# (the same floor as stage two's noise level, latentsindy._stage_two.context.NOISE_FLOOR).
FLOOR = 1e-3
_MIN_SAMPLES = 12


def discount(x, t):
    """``(mask, cleaned)``: the rows of ``x`` (n, n_states) holding an isolated spike in
    any state, and ``x`` with each such value replaced by its neighbours' cubic."""
    x = np.array(x, dtype=float)
    t = np.asarray(t, dtype=float)
    mask = np.zeros(len(x), dtype=bool)
    if len(x) < _MIN_SAMPLES:
        return mask, x
    weights, gain = _neighbour_weights(t)
    for _ in range(PASSES):
        found = False
        for j in range(x.shape[1]):
            rows, x[:, j] = _spikes(x[:, j], t, weights, gain)
            mask[rows] = True
            found = found or bool(len(rows))
        if not found:
            break
    return mask, x


def _neighbour_weights(t):
    """Lagrange weights of the cubic through samples k-2, k-1, k+1, k+2 at t[k], for
    k = 2 .. n-3 (rows), and the noise gain sqrt(1 + sum w^2) of each residual."""
    k = np.arange(2, len(t) - 2)
    nodes = np.stack([t[k - 2], t[k - 1], t[k + 1], t[k + 2]], axis=1)
    at = t[k][:, None]
    w = np.ones_like(nodes)
    for i in range(4):
        for m in range(4):
            if m != i:
                w[:, i] *= (at[:, 0] - nodes[:, m]) / (nodes[:, i] - nodes[:, m])
    return w, np.sqrt(1.0 + np.sum(w**2, axis=1))


def _predict(x, w, k):
    return float(w[k - 2] @ x[[k - 2, k - 1, k + 1, k + 2]])


def _local_spread(r):
    """Robust spread of the residuals around each sample: the whole series' (1.4826
    times the median of ``|r|``), or where the spread over the ``WINDOW`` samples around
    it is more than ``LOCAL`` times that, the local one. Noise whose level follows the
    signal (counts, multiplicative noise) is then judged at its level there, while white
    noise is judged by the precise whole-series spread (a local median over ~100
    correlated residuals strays by 20-40%, which would hide spikes or invent them)."""
    whole = 1.4826 * float(np.median(np.abs(r)))
    n = len(r)
    if n <= WINDOW:
        return np.full(n, whole)
    half = WINDOW // 2
    size = np.abs(r)
    bar = LOCAL * whole
    # a window's spread exceeds the bar only where half its samples' do (rounding is
    # monotone, so an odd window's median of the products is the product of its median):
    # only those windows are sorted, the others keep the whole spread (white noise: none
    # of them; 20,000 samples took 0.08 s to sort every window)
    above = np.concatenate([[0], np.cumsum(1.4826 * size > bar)])
    sort = np.flatnonzero(above[WINDOW:] - above[:-WINDOW] >= (WINDOW + 1) // 2)
    med = np.zeros(n - WINDOW + 1)
    if len(sort):
        windows = np.lib.stride_tricks.sliding_window_view(size, WINDOW)
        med[sort] = 1.4826 * np.median(windows[sort], axis=1)
    local = np.concatenate([np.full(half, med[0]), med,
                            np.full(n - len(med) - half, med[-1])])
    return np.where(local > bar, local, whole)


def _residuals(x, w, gain):
    """Scaled residual of every sample k = 2 .. n-3 (0 at the two ends)."""
    r = np.zeros(len(x))
    neighbours = np.stack([x[:-4], x[1:-3], x[3:-1], x[4:]], axis=1)
    r[2:-2] = (x[2:-2] - np.sum(w * neighbours, axis=1)) / gain
    return r


def _spikes(x, t, w, gain):
    """The rows of one state's isolated spikes (see the module) and the state with
    each replaced by the cubic through the samples around it."""
    r = _residuals(x, w, gain)
    s = _local_spread(r[2:-2])
    if not np.median(s) > 1e-12 * max(float(np.std(x)), 1e-300):
        return [], x
    limit = np.zeros(len(x))
    limit[2:-2] = np.maximum(Z * s, FLOOR * float(np.std(x)))
    limit[:2], limit[-2:] = limit[2], limit[-3]
    found, x = set(), x.copy()
    candidates = np.flatnonzero(np.abs(r) > limit)
    for k in candidates[np.argsort(-np.abs(r[candidates]))]:
        if abs(r[k]) <= limit[k] or k in found:
            continue  # (residuals change as spikes beside them are replaced)
        for rows in _sets(k, len(x)):
            if found.intersection(rows):
                continue
            values = _replaced(x, t, w, gain, rows, limit)
            if values is not None:
                x[rows] = values
                found.update(rows)
                for i in range(max(2, rows[0] - 2), min(len(x) - 3, rows[-1] + 2) + 1):
                    r[i] = (x[i] - _predict(x, w, i)) / gain[i - 2]
                break
    return sorted(found), x


_HALF = 4  # samples on either side of a spike (or pair) that the cubic is fitted to


def _sets(k, n):
    """The rows tried as isolated spikes around a sample off the curve: the sample
    alone, then pairs of samples up to four apart holding it or on either side of it
    (a second spike within two samples moves the first one's prediction)."""
    yield [k]
    pairs = [(k, k + d) for d in range(1, 5)] + [(k - d, k) for d in range(1, 5)]
    pairs += [(k - a, k + b) for a in range(1, 4) for b in range(1, 4) if a + b <= 4]
    for a, b in sorted(pairs, key=lambda p: p[1] - p[0]):
        if a >= 2 and b <= n - 3:
            yield [a, b]


def _replaced(x, t, w, gain, rows, limit):
    """The values of ``rows`` on the least-squares cubic through the samples within
    :data:`_HALF` of them, or None where they are not isolated spikes: those samples
    lie on the cubic (within half the limit: its residuals' spread is about 0.7 noise
    levels, so 3.5 spreads), each of ``rows`` is off it beyond the limit
    (two adjacent ones in opposite directions: two samples off to one side are a narrow
    feature of the curve) and, replaced, every sample from two before to two after is
    on the curve (its residual below half the limit), as the module says."""
    n = len(x)
    lo, hi = max(0, rows[0] - _HALF), min(n, rows[-1] + _HALF + 1)
    window = [i for i in range(lo, hi) if i not in rows]
    if len(window) < 6:
        return None
    tau = t[window] - t[rows[0]]
    scale = max(float(np.max(np.abs(tau))), 1e-300)
    basis = np.vander(tau / scale, 4)
    coef, *_ = np.linalg.lstsq(basis, x[window], rcond=None)
    if np.any(np.abs(x[window] - basis @ coef) > limit[window] / 2):
        return None
    at = np.vander((t[rows] - t[rows[0]]) / scale, 4) @ coef
    off = x[rows] - at
    if np.any(np.abs(off) <= limit[rows]):
        return None
    if len(rows) == 2 and rows[1] - rows[0] == 1 and off[0] * off[1] > 0:
        return None
    local = x[lo:hi].copy()  # (the residuals below reach two samples further at most)
    local[np.asarray(rows) - lo] = at
    after = [abs(local[i - lo] - w[i - 2] @ local[[i - 2 - lo, i - 1 - lo, i + 1 - lo,
                                                   i + 2 - lo]]) / gain[i - 2]
             for i in range(max(2, rows[0] - 2), min(n - 3, rows[-1] + 2) + 1)]
    return at if max(after) < min(limit[rows]) / 2 else None
