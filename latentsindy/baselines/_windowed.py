"""Windowed SINDy with one sparsity pattern across windows (seed paper, supplement 4.2).

The series is cut into M windows of equal length; SINDy is solved on each window while
every term is either on in all windows or off in all of them. Two published ways to
choose that shared support:

* ``method="group"``: the l_{2,0} group-sparse problem
  ``min sum_i ||Theta_i xi_i - xdot_i||^2 + gamma * #{terms whose coefficients across
  windows are not all zero}``, solved by the supplement's group hard-iterative
  thresholding: a gradient step in every window from the current coefficients, then
  the support becomes the terms whose root-mean-square coefficient across windows
  reaches ``threshold`` (``gamma = M * threshold^2`` in normalised units; a term may
  leave or come back), then a least-squares refit on that support, until the support
  stops changing. From the least-squares start the step leaves kept terms unchanged
  (their gradient is zero) and offers pruned ones back through the residual.
* ``method="stlsq"``: sequential thresholding on each term's coefficient averaged (in
  absolute value) over windows; the supplement found it the more effective of the two.

Coefficients are compared with ``threshold`` in normalised units, as in
:class:`latentsindy.DynamicSINDy`: library columns scaled to unit RMS and each
derivative to unit RMS, so a coefficient is the share of its equation's RMS derivative
it explains. Normalising makes the default independent of units (the supplement
reports the unnormalised version as better on its own systems; pass a large or small
threshold accordingly, or rescale the data).
"""

from __future__ import annotations

import copy

import numpy as np

from .._core import validation as val
from .._core.differentiation import differentiate
from .._core.library import check_library, fit_library
from .._stage_one.coefficients import CoefficientSeries
from ._inputs import one_trajectory

_METHODS = ("stlsq", "group")
_INTERPOLATIONS = ("linear", "constant")


class WindowedSINDy:
    """Group-sparse windowed SINDy: the baseline dynamic SINDy is compared with.

    Parameters
    ----------
    library : pysindy feature library, optional
        Default ``PolynomialLibrary(degree=2)``.
    n_windows : int, optional
        Number of windows M. Default: the M among 2, 4, 8, ... (each window keeping at
        least ``5 * n_features`` and 20 samples) whose windows best predict their
        neighbours: every window's derivatives are predicted with the mean coefficients
        of the windows beside it, which were fitted on other data. Too few windows miss
        the variation; too many leave short, ill-conditioned windows whose coefficients
        jump from one to the next. (Held-out samples inside a window do not work as a
        criterion: smoothed derivatives are correlated, and any local fit predicts its
        own window's gaps, so it picks the most windows.) M = 1 is never chosen by
        default: coefficients that do not vary come out nearly equal in two windows.
    method : {"stlsq", "group"}
        Averaged-coefficient sequential thresholding, or group hard thresholding.
    threshold : float
        Smallest normalised coefficient (mean absolute value over windows for ``"stlsq"``, RMS
        over windows for ``"group"``) a term may keep.
    max_iter : int
        Thresholding iterations (the supplement uses 100).
    interpolation : {"constant", "linear"}
        Coefficients constant within each window (what the method fits), or linear
        between window centres.
    differentiation_method : pysindy differentiation object, optional
        Used when ``x_dot`` is not given (default: noise-adaptive Savitzky-Golay).

    Attributes
    ----------
    n_windows_ : int
    edges_ : ndarray of int (n_windows + 1,)
        Sample index where each window starts (last: n_times).
    window_coef_ : ndarray (n_windows, n_states, n_features)
    support_ : ndarray of bool (n_states, n_features)
    cv_errors_ : dict {M: neighbour-prediction error} (empty when n_windows was given)

    Examples
    --------
    >>> import pysindy as ps
    >>> from latentsindy import systems
    >>> from latentsindy.baselines import WindowedSINDy
    >>> data = systems.harmonic_oscillator(A=systems.Switch(-1.0, -4.0, at=12.5), B=1.0,
    ...                                    n_times=1000, t_end=25.0)
    >>> model = WindowedSINDy(ps.PolynomialLibrary(degree=1, include_bias=False),
    ...                       n_windows=10).fit(data.x, data.t, feature_names=["x", "y"])
    >>> model.coefficients().term("x", "y")[[0, -1]].round(2).tolist()
    [-1.0, -4.0]
    """

    def __init__(self, library=None, *, n_windows=None, method="stlsq", threshold=0.05,
                 max_iter=100, interpolation="constant", differentiation_method=None):
        self.library = library
        self.n_windows = n_windows
        self.method = method
        self.threshold = threshold
        self.max_iter = max_iter
        self.interpolation = interpolation
        self.differentiation_method = differentiation_method

    def fit(self, x, t, *, x_dot=None, feature_names=None) -> WindowedSINDy:
        """Fit one trajectory ``x`` (n_times, n_states) sampled at ``t`` (array or step)."""
        if self.method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}; got {self.method!r}.")
        if self.interpolation not in _INTERPOLATIONS:
            raise ValueError(f"interpolation must be one of {_INTERPOLATIONS}; got "
                             f"{self.interpolation!r}.")
        val.check_positive(self.threshold, "threshold", allow_zero=True)
        val.check_positive(self.max_iter, "max_iter", integer=True)
        (traj,) = one_trajectory(x, "WindowedSINDy fits")
        (times,) = val.as_times(t, [traj])
        names = val.check_feature_names(feature_names, traj.shape[1])
        library = check_library(self.library)
        (theta,), features = fit_library(library, [traj], names)
        if x_dot is None:  # a copy: the user's differentiation object is never mutated
            (xdot,), _, _ = differentiate(copy.deepcopy(self.differentiation_method),
                                          [traj], [times])
        else:
            (xdot,) = val.as_trajectories(x_dot, "x_dot")
            if xdot.shape != traj.shape:
                raise ValueError(f"x_dot must have the shape of x {traj.shape}; got "
                                 f"{xdot.shape}.")
        n, p = theta.shape
        min_len = max(20, 5 * p)
        if n < min_len:
            raise ValueError(f"need at least {min_len} samples for {p} library features; "
                             f"got {n}.")
        col = np.sqrt(np.mean(theta**2, axis=0))
        col[col == 0] = 1.0
        rms = np.sqrt(np.mean(xdot**2, axis=0))
        rms[rms == 0] = 1.0
        a, b = theta / col, xdot / rms
        if self.n_windows is None:
            if n // 2 < min_len:
                raise ValueError(f"need at least {2 * min_len} samples to choose the number "
                                 f"of windows for {p} features; got {n}. Pass n_windows=1.")
            self.cv_errors_ = _neighbour_errors(a, b, min_len, self._solve)
            m = min(self.cv_errors_, key=self.cv_errors_.get)
        else:
            m = val.check_positive(self.n_windows, "n_windows", integer=True)
            if n // m < min_len:
                raise ValueError(f"n_windows={m} leaves {n // m} samples per window; each "
                                 f"needs >= {min_len} for {p} features. Use fewer windows.")
            self.cv_errors_ = {}
        edges = _edges(n, m)
        coef, support = self._solve(a, b, edges)
        self.n_windows_ = m
        self.edges_ = edges
        self.window_coef_ = coef * rms[None, :, None] / col[None, None, :]
        self.support_ = support
        self.times_ = times
        self.state_names_ = tuple(names)
        self.feature_names_ = tuple(features)
        return self

    def coefficients(self) -> CoefficientSeries:
        """The coefficients at every sample time (one sample, zero spread)."""
        if not hasattr(self, "window_coef_"):
            raise RuntimeError("WindowedSINDy is not fitted; call fit(x, t) first.")
        n = self.times_.size
        if self.interpolation == "constant" or self.n_windows_ == 1:
            idx = np.searchsorted(self.edges_, np.arange(n), side="right") - 1
            mean = self.window_coef_[idx]
        else:
            centres = 0.5 * (self.edges_[:-1] + self.edges_[1:] - 1)
            flat = self.window_coef_.reshape(self.n_windows_, -1)
            mean = np.stack([np.interp(np.arange(n), centres, c) for c in flat.T],
                            axis=1).reshape((n,) + self.window_coef_.shape[1:])
        return CoefficientSeries.from_samples(self.times_, mean, mean[None],
                                              self.state_names_, self.feature_names_,
                                              self.support_, self.support_.copy())

    # ---------------------------------------------------------------- solvers
    def _solve(self, a, b, edges):
        """Per-window coefficients (M, n_states, n_features) and the shared support."""
        blocks = [(a[lo:hi], b[lo:hi]) for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
        p, n_states = a.shape[1], b.shape[1]
        coef = np.zeros((len(blocks), n_states, p))
        support = np.ones((n_states, p), dtype=bool)
        step = (1.0 / max(np.linalg.norm(theta, 2) ** 2 for theta, _ in blocks)
                if self.method == "group" else 0.0)
        for j in range(n_states):
            keep = np.ones(p, dtype=bool)
            xi = _lstsq(blocks, j, keep)
            for _ in range(int(self.max_iter)):
                if self.method == "group":  # gradient step, then group hard threshold
                    xi = np.stack([x - step * th.T @ (th @ x - rhs[:, j])
                                   for x, (th, rhs) in zip(xi, blocks, strict=True)])
                    new = np.sqrt(np.mean(xi**2, axis=0)) >= self.threshold
                else:  # sequential thresholding of window-averaged |coefficients|
                    new = keep & (np.mean(np.abs(xi), axis=0) >= self.threshold)
                xi = _lstsq(blocks, j, new)
                if np.array_equal(new, keep):
                    break
                keep = new
            coef[:, j] = xi
            support[j] = keep
        return coef, support


def _lstsq(blocks, j, keep):
    out = np.zeros((len(blocks), keep.size))
    if keep.any():
        for i, (theta, rhs) in enumerate(blocks):
            out[i, keep] = np.linalg.lstsq(theta[:, keep], rhs[:, j], rcond=None)[0]
    return out


def _edges(n, m):
    return np.round(np.linspace(0, n, m + 1)).astype(int)


def _neighbour_errors(a, b, min_len, solve):
    """Error of predicting each window from its neighbours' coefficients, for M = 2, 4,
    8, ... windows (normalised units, per sample)."""
    n = a.shape[0]
    errors = {}
    m = 2
    while n // m >= min_len:
        edges = _edges(n, m)
        coef, _ = solve(a, b, edges)
        total = 0.0
        for i in range(m):
            neighbours = [k for k in (i - 1, i + 1) if 0 <= k < m]
            guess = coef[neighbours].mean(axis=0)
            lo, hi = edges[i], edges[i + 1]
            total += float(np.sum((a[lo:hi] @ guess.T - b[lo:hi]) ** 2))
        errors[m] = total / b.size
        m *= 2
    return errors
