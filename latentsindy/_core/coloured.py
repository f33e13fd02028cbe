"""Coloured measurement noise: the level and the sample-to-sample correlation of AR(1)
noise (sensors and filters make noise correlated in time), read from the data.

Differences of neighbouring samples see only the fast part of correlated noise: AR(1)
noise with correlation 0.9 between samples gives 4th differences of 6% of white
noise's variance, so its level reads 4 times too low, and every misfit measured in it
reads 16 times too high (a right law looks wrong; more hidden states are added). The
4th difference taken ``m`` samples apart has variance ``sigma^2 g(phi^m)`` for AR(1)
noise, with ``g(q) = 70 - 112 q + 56 q^2 - 16 q^3 + 2 q^4`` (white noise: 70 at every
``m``), while a smooth signal's grows like ``m^8``. The noise is read as AR(1) when
these variances for ``m = 1 .. M`` follow ``g`` closely (log-space misfit under
:data:`FIT`) with a correlation between :data:`LOW` and :data:`HIGH` (below 0.4 a fast
signal can read as weak correlation: the Hindmarsh-Rose neuron's spiking state, 8000
samples at 1% noise, read 0.32); otherwise (white noise, a signal that the spacings
already resolve, or a correlation too high for 8 spacings to tell its level: above
about 0.9) it is white, and nothing changes. No benchmark family at 0-10% white
noise, and none of the systems module's or five fresh systems (Hindmarsh-Rose, van
der Pol, Rossler, Brusselator) at 0-5%, reads as coloured.
"""

from __future__ import annotations

import numpy as np

from .local_fits import is_uniform

M = 8  # spacings 1 .. M of the dilated 4th differences
LOW, HIGH = 0.4, 0.95  # correlations read as coloured noise (edges: white, or unresolved)
FIT = 0.1  # largest log-space misfit of the AR(1) variance curve
_PHIS = np.linspace(0.0, 0.98, 99)
_G = np.array([70.0, -112.0, 56.0, -16.0, 2.0])


def ar1_noise(x, t=None):
    """Per column of ``x`` (or of a list of recordings, pooled): ``(sigma, phi)``, the
    marginal standard deviation and the correlation between neighbouring samples of
    AR(1) noise, or ``phi = 0`` (and ``sigma`` None) where the noise does not read as
    coloured. Uniform sampling only (irregular times: white)."""
    xs = list(x) if isinstance(x, list | tuple) else [x]
    ts = list(t) if isinstance(t, list | tuple) else [t] * len(xs)
    xs = [np.asarray(a, float) for a, tk in zip(xs, ts, strict=True)
          if tk is None or np.ndim(tk) == 0 or is_uniform(tk)]
    xs = [a for a in xs if len(a) > 4 * M + 16]
    n_cols = np.asarray(x[0] if isinstance(x, list | tuple) else x).shape[1]
    sigma, phi = [None] * n_cols, np.zeros(n_cols)
    if not xs:
        return sigma, phi
    ms = np.arange(1, M + 1)
    for j in range(n_cols):
        v = np.array([_robust_var(np.concatenate([_dilated(a[:, j], m) for a in xs]))
                      for m in ms])
        if not np.all(v > 0):
            continue
        best = min((_misfit(np.log(v), p ** ms), p) for p in _PHIS)
        (err, level), p = best
        if err < FIT and LOW <= p <= HIGH:
            sigma[j], phi[j] = float(np.exp(level / 2)), float(p)
    return sigma, phi


def _dilated(col, m):
    return (col[4 * m:] - 4 * col[3 * m:-m] + 6 * col[2 * m:-2 * m] - 4 * col[m:-3 * m]
            + col[:-4 * m])


def _robust_var(d):
    return float((1.4826 * np.median(np.abs(d - np.median(d)))) ** 2)


def _misfit(log_v, q):
    """(log-space misfit, log sigma^2) of variances ``exp(log_v)`` against
    ``sigma^2 g(q)`` with the best ``sigma``."""
    log_g = np.log(np.polyval(_G[::-1], q))
    level = float(np.mean(log_v - log_g))
    return float(np.sum((log_v - level - log_g) ** 2)), level
