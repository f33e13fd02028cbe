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
samples at 1% noise, read 0.32). A signal's share raises the wider spacings' variances
as a higher correlation would (AR(1) 0.9 under an oscillation of about 100 samples a
cycle read 0.96-0.98 in 6 of 20 states, and was taken for white): where noise alone
does not read as coloured, the variances are read again with a signal's share
``b m^8`` beside the noise's, on ``M`` and then :data:`M_WIDE` spacings. Otherwise
(white noise, a signal that the spacings already resolve, or a correlation too high
to tell its level) it is white, and nothing changes. No benchmark family at 0-10% white
noise, and none of the systems module's or five fresh systems (Hindmarsh-Rose, van
der Pol, Rossler, Brusselator) at 0-5%, reads as coloured.
"""

from __future__ import annotations

import functools

import numpy as np

from .fingerprint import fingerprint
from .local_fits import is_uniform

M = 8  # spacings 1 .. M of the dilated 4th differences
M_WIDE = 12  # spacings of the last reading (_ar1_signal_fit), for correlations near HIGH
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
    n_cols = np.asarray(x[0] if isinstance(x, list | tuple) else x).shape[1]
    key = (n_cols, *(fingerprint(a) for a in xs))
    if key not in _READ:
        if len(_READ) >= 32:
            _READ.clear()
        _READ[key] = _ar1_noise(xs, n_cols)
    sigma, phi = _READ[key]
    return list(sigma), phi.copy()


# the readings of the recordings seen last, by content: a discovery reads the same
# recording's noise again and again (every refinement problem of every hypothesis:
# 25 readings of 11 distinct recordings on prey-only LV over 20,000 samples, 0.14 s)
_READ: dict = {}


def _ar1_noise(xs, n_cols):
    """:func:`ar1_noise` of the uniform recordings ``xs`` (float arrays)."""
    sigma, phi = [None] * n_cols, np.zeros(n_cols)
    read = {}  # the variances of one column at one spacing over the same recordings,
    # read once: the three fits share their spacings (28 medians of 2,000 values -> 12)
    for fit, spacings in ((_ar1_fit, M), (_ar1_signal_fit, M), (_ar1_signal_fit, M_WIDE)):
        usable = tuple(k for k, a in enumerate(xs) if len(a) > 4 * spacings + 16)
        ms = np.arange(1, spacings + 1)
        for j in np.flatnonzero(phi == 0) if usable else ():
            for m in ms:
                if (usable, j, m) not in read:
                    read[usable, j, m] = _robust_var(np.concatenate(
                        [_dilated(xs[k][:, j], m) for k in usable]))
            v = np.array([read[usable, j, m] for m in ms])
            if not np.all(v > 0):
                continue
            err, level, p = fit(v, ms)
            if err < FIT * spacings / M and LOW <= p <= HIGH:  # FIT: per 8 spacings
                sigma[j], phi[j] = float(np.exp(level / 2)), float(p)
    return sigma, phi


def with_ar1(white, x, t=None) -> tuple[np.ndarray, np.ndarray]:
    """``(sigma, phi)`` per column: the white levels ``white``, with AR(1) noise's
    marginal level where :func:`ar1_noise` reads the noise of ``x`` as coloured."""
    coloured, phi = ar1_noise(x, t)
    sigma = np.array([c if c is not None else w for c, w in zip(coloured, white,
                                                                 strict=True)])
    return sigma, np.asarray(phi, float)


def ar1_gain(coeffs, phi: float) -> float:
    """Variance gain of the linear filter ``coeffs`` on AR(1) noise of unit variance and
    correlation ``phi`` between neighbouring samples (``sum c_i c_j phi^|i-j|``; white
    noise: ``sum c_i^2``)."""
    c = np.asarray(coeffs, float)
    if phi <= 0:
        return float(np.sum(c**2))
    lags = np.abs(np.subtract.outer(np.arange(len(c)), np.arange(len(c))))
    return float(c @ (phi**lags) @ c)


def _ar1_fit(v, ms):
    """(misfit, log sigma^2, phi): the variances ``v`` at spacings ``ms`` as AR(1)
    noise alone (every correlation of the grid at once)."""
    log_g = _g_table(len(ms))[1]
    levels = np.mean(np.log(v) - log_g, axis=1)
    errs = np.sum((np.log(v) - levels[:, None] - log_g) ** 2, axis=1)
    k = int(np.argmin(errs))
    return float(errs[k]), float(levels[k]), float(_PHIS[k])


def _ar1_signal_fit(v, ms):
    """As :func:`_ar1_fit`, with a smooth signal's share ``b m^8`` added to the noise's
    (both non-negative; weighted least squares in relative units). The signal raises
    the wider spacings' variances as a higher correlation would: where noise alone
    reads a correlation above :data:`HIGH` or misses the curve (AR(1) 0.9 under an
    oscillation of about 100 samples per cycle: 0.96-0.98 in 6 of 20 states), this
    reads it again with the signal taken out, on :data:`M` and then on :data:`M_WIDE`
    spacings (18 of those 20 states, 0.80-0.94, the level 0.7-1.3 of the truth).

    The two-coefficient non-negative least squares is solved in closed form for every
    correlation of the grid at once: the unconstrained solution where both are
    positive, else the better of the two one-coefficient fits (both positive: the
    columns are)."""
    g = _g_table(len(ms))[0]  # (P, M)
    signal = (ms / ms[-1]) ** 8
    scale = float(np.max(v))  # in units of the largest variance: any scale reads alike
    v = v / scale
    a0, a1 = g / v, signal / v  # weighted columns: (P, M), (M,)
    n0, n1 = np.sqrt(np.sum(a0 * a0, axis=1)), float(np.sqrt(a1 @ a1))
    r = (a0 @ a1) / (n0 * n1)  # the columns' cosine: the unit-column Gram is [[1, r], [r, 1]]
    b0, b1 = np.sum(a0, axis=1) / n0, float(np.sum(a1)) / n1
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        u0, u1 = (b0 - r * b1) / (1 - r * r), (b1 - r * b0) / (1 - r * r)
        inside = np.isfinite(u0) & np.isfinite(u1) & (u0 > 0) & (u1 > 0)
        # on the boundary: noise alone or signal alone, whichever leaves less residual
        noise_alone = b0 >= b1
        c0 = np.where(inside, u0, np.where(noise_alone, b0, 0.0)) / n0
        c1 = np.where(inside, u1, np.where(noise_alone, 0.0, b1)) / n1
        model = c0[:, None] * g + c1[:, None] * signal
        errs = np.sum(np.log(v / model) ** 2, axis=1)
    errs[~((c0 > 0) & np.isfinite(errs))] = np.inf
    k = int(np.argmin(errs))
    if not np.isfinite(errs[k]):
        return np.inf, 0.0, 0.0
    return float(errs[k]), float(np.log(c0[k]) + np.log(scale)), float(_PHIS[k])


@functools.cache
def _g_table(spacings):
    """``g(phi^m)`` and its log for every correlation of the grid (rows) and spacing
    ``m = 1 .. spacings`` (columns)."""
    g = np.polyval(_G[::-1], _PHIS[:, None] ** np.arange(1, spacings + 1))
    log_g = np.log(g)
    g.flags.writeable = log_g.flags.writeable = False
    return g, log_g


def _dilated(col, m):
    return (col[4 * m:] - 4 * col[3 * m:-m] + 6 * col[2 * m:-2 * m] - 4 * col[m:-3 * m]
            + col[:-4 * m])


def _robust_var(d):
    return float((1.4826 * np.median(np.abs(d - np.median(d)))) ** 2)
