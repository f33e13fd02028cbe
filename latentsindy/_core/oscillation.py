"""How long a series takes to oscillate: the mean time between upward crossings of its
mean, with a hysteresis of a quarter standard deviation so that noise makes no
crossings."""

from __future__ import annotations

import numpy as np


def crossing_periods(x, t) -> list[float]:
    """The crossing period of each column of ``x`` (n_times, n) on the times ``t``;
    columns with fewer than two upward crossings are left out.

    Examples
    --------
    >>> t = np.linspace(0.0, 10.0, 1001)
    >>> [round(p, 3) for p in crossing_periods(np.sin(2 * np.pi * t)[:, None], t)]
    [1.0]
    """
    t = np.asarray(t, dtype=float)
    out = []
    for col in np.asarray(x, dtype=float).reshape(len(t), -1).T:
        c = (col - col.mean()) / max(float(col.std()), 1e-300)
        ups, low = [], False
        for k in np.flatnonzero((c < -0.25) | (c > 0.25)):
            if c[k] < 0:
                low = True
            elif low:
                ups.append(k)
                low = False
        if len(ups) >= 2:
            out.append(float(np.mean(np.diff(t[ups]))))
    return out
