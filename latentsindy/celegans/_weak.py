"""Weak-form regression for ``xddot = a x^3 + b x^2 + c x + d xdot + u(t)``.

Each equation is tested against smooth bumps ``phi(t) = (1 - s^2)^4`` on short windows
and integrated by parts twice, so no derivative of the noisy data is ever taken
(weak SINDy, Messenger & Bortz 2021):

    int phi'' x dt = a int phi x^3 + b int phi x^2 + c int phi x - d int phi' x + int phi u.

With u a two-level switch the right side is linear in (a, b, c, d, u_low, u_high), and
several recordings share (a, b, c, d) while each keeps its own levels: one stacked
least-squares problem. The bump's half-width follows the data's spectrum: the corner
where the power spectrum meets its noise floor sets the shortest period the data
resolve, and the bump spans that period (never fewer than 8 samples either side, where
the quadrature is exact enough).
"""

from __future__ import annotations

import numpy as np

_POWER = 4
MIN_HALF_WIDTH = 8


def half_width(x: np.ndarray) -> int:
    """Test-function half-width (samples) from the spectrum's noise corner."""
    x = np.asarray(x, dtype=float)
    n = x.size
    detrended = x - np.linspace(x[0], x[-1], n)  # no jump at the periodic extension
    logp = np.log(np.abs(np.fft.rfft(detrended))[1:] ** 2 + 1e-300)
    k = np.arange(1, logp.size + 1)
    if logp.size < 16:
        return MIN_HALF_WIDTH
    # two pieces: a power law down to the corner, then a flat noise floor
    suffix_mean = np.cumsum(logp[::-1])[::-1] / np.arange(logp.size, 0, -1)
    suffix_sq = np.cumsum((logp**2)[::-1])[::-1]
    best, corner = np.inf, logp.size // 2
    design = np.column_stack([np.ones_like(logp), np.log(k)])
    for j in range(4, logp.size - 4, max(1, logp.size // 400)):
        coef, *_ = np.linalg.lstsq(design[:j], logp[:j], rcond=None)
        head = float(np.sum((design[:j] @ coef - logp[:j]) ** 2))
        tail = float(suffix_sq[j] - (logp.size - j) * suffix_mean[j] ** 2)
        if head + tail < best:
            best, corner = head + tail, j
    period = n / k[corner]
    return int(np.clip(round(period / 2), MIN_HALF_WIDTH, max(MIN_HALF_WIDTH, n // 20)))


def _bumps(m: int, dt: float):
    s = np.arange(-m, m + 1) / m
    base = 1.0 - s**2
    phi = base**_POWER
    dphi = _POWER * base ** (_POWER - 1) * (-2.0 * s) / (m * dt)
    ddphi = (_POWER * (_POWER - 1) * base ** (_POWER - 2) * 4.0 * s**2
             - 2.0 * _POWER * base ** (_POWER - 1)) / (m * dt) ** 2
    return phi * dt, dphi * dt, ddphi * dt  # rectangle rule; phi vanishes at both ends


def _windows(x, m, stride):
    win = np.lib.stride_tricks.sliding_window_view(x, 2 * m + 1)
    return win[::stride]


def weak_rows(x, labels, dt, m, stride=None):
    """Rows of the weak problem for one recording: (A (k, 6), b (k,)). Columns are
    x^3, x^2, x, xdot, u_low, u_high."""
    stride = stride or max(1, m // 2)
    phi, dphi, ddphi = _bumps(m, dt)
    w = _windows(np.asarray(x, dtype=float), m, stride)
    lab = _windows(np.asarray(labels), m, stride)
    a = np.column_stack([(w**3) @ phi, (w**2) @ phi, w @ phi, -(w @ dphi),
                         (lab == 0) @ phi, (lab == 1) @ phi])
    return a, w @ ddphi


def fit_shared(xs, labels, dts, m):
    """Shared (a, b, c, d) and per-recording levels; returns (constants (4,), levels
    (n_rec, 2), standard errors of the constants (4,), residual RMS)."""
    blocks, rhs = [], []
    n_rec = len(xs)
    for i, (x, lab, dt) in enumerate(zip(xs, labels, dts, strict=True)):
        a, b = weak_rows(x, lab, dt, m)
        full = np.zeros((a.shape[0], 4 + 2 * n_rec))
        full[:, :4] = a[:, :4]
        full[:, 4 + 2 * i: 6 + 2 * i] = a[:, 4:]
        blocks.append(full)
        rhs.append(b)
    a, b = np.vstack(blocks), np.concatenate(rhs)
    keep = np.any(a != 0, axis=0)  # a level never visited has no column
    sol = np.zeros(a.shape[1])
    sol[keep], *_ = np.linalg.lstsq(a[:, keep], b, rcond=None)
    resid = b - a @ sol
    dof = max(1, b.size - int(keep.sum()))
    s2 = float(resid @ resid) / dof
    # neighbouring test functions overlap (stride m/2, width 2m + 1), so each sample
    # enters about (2m + 1) / stride rows: their residuals are correlated and the
    # independent-rows covariance is too small by about that factor
    overlap = (2 * m + 1) / max(1, m // 2)
    cov = overlap * s2 * np.linalg.pinv(a[:, keep].T @ a[:, keep])
    se = np.sqrt(np.clip(np.diag(cov)[:4], 0.0, None))
    levels = sol[4:].reshape(n_rec, 2)
    for i, lab in enumerate(labels):  # an unvisited level keeps the visited one
        for k in (0, 1):
            if not np.any(np.asarray(lab) == k):
                levels[i, k] = levels[i, 1 - k]
    return sol[:4], levels, se, float(np.sqrt(s2))


def local_input(x, dt, constants, m):
    """u(t) seen through one bump at every sample (edges repeat the nearest value)."""
    x = np.asarray(x, dtype=float)
    a, b, c, d = constants
    phi, dphi, ddphi = _bumps(m, dt)
    w = _windows(x, m, 1)
    inner = (w @ ddphi - a * (w**3) @ phi - b * (w**2) @ phi - c * (w @ phi)
             + d * (w @ dphi)) / phi.sum()
    return np.concatenate([np.full(m, inner[0]), inner, np.full(m, inner[-1])])
