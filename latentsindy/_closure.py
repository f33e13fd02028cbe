"""Equations for the hidden states: pysindy with a threshold chosen by held-out error."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pysindy as ps

N_FOLDS = 5
TOLERANCE = 0.05  # a sparser model is accepted within max(1 standard error, 5%) of the best
N_THRESHOLDS = 30


def fit_closure(hidden, hidden_dot, observed, times, library, hidden_names, observed_names,
                span=1):
    """Fit ``d hidden/dt = f(hidden, observed)`` with pysindy's STLSQ.

    STLSQ (normalised columns, unbiased) is run along a geometric grid of thresholds;
    every distinct support is scored by cross-validation over contiguous time blocks,
    and the sparsest support whose held-out error is within one standard error (across
    folds; at least 5%) of the best wins: the "one-standard-error rule". No threshold
    needs tuning, and terms that only fit noise do not beat it.

    Candidate supports come from STLSQ on the pointwise derivatives and are scored on
    them; the final coefficients (least squares on the chosen support) use the
    integral form: ``h(t + span) - h(t)`` against the integral of the library over the
    same interval (trapezoid), on every interval of ``span`` samples. That needs no
    derivative of h and averages out errors of h on scales shorter than ``span`` (the
    stage-one data resolve nothing finer than their derivative's smoothing window).

    Returns
    -------
    model : ps.SINDy
        Fitted on the hidden states with the observed states as inputs ``u``; its
        features are named after ``hidden_names + observed_names``.
    table : list of (threshold, n_terms, cv_error)
    """
    hidden = [np.asarray(h, dtype=float) for h in hidden]
    observed = [np.asarray(u, dtype=float) for u in observed]
    hidden_dot = [np.asarray(d, dtype=float) for d in hidden_dot]
    names = list(hidden_names) + list(observed_names)
    target = np.vstack(hidden_dot)
    candidates, seen = [], set()
    top = None
    for thr in [0.0, *np.geomspace(1e-4, 1.0, N_THRESHOLDS)]:
        model = _fit(thr * (top or 1.0), hidden, hidden_dot, observed, times, library, names)
        coef = model.coefficients()
        if top is None:  # scale the grid to the largest least-squares coefficient
            top = _normalised_max(model, hidden, observed)
        key = tuple(map(tuple, coef != 0))
        if key in seen:
            continue
        seen.add(key)
        theta = np.vstack([np.asarray(a) for a in model.feature_library.transform(
            [np.hstack([h, u]) for h, u in zip(hidden, observed, strict=True)])])
        err, se = _cv_error(theta, target, coef != 0)
        candidates.append((thr * (top or 1.0), int((coef != 0).sum()), err, se, model))
    best = min(candidates, key=lambda c: c[2])
    limit = best[2] + max(best[3], TOLERANCE * best[2])
    ok = [c for c in candidates if c[2] <= limit]
    chosen = min(ok, key=lambda c: (c[1], c[2]))
    model = chosen[4]
    _refit_integral(model, hidden, observed, times, span)
    table = [(c[0], c[1], c[2]) for c in candidates]
    return model, table


def _fit(threshold, hidden, hidden_dot, observed, times, library, names):
    model = ps.SINDy(
        optimizer=ps.STLSQ(threshold=threshold, alpha=1e-10, normalize_columns=True,
                           max_iter=50),
        feature_library=copy.deepcopy(library),
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # STLSQ warns when a threshold empties a row
        model.fit(hidden, t=list(times), x_dot=hidden_dot, u=observed, feature_names=names)
    return model


def _normalised_max(model, hidden, observed):
    theta = np.vstack([np.asarray(a) for a in model.feature_library.transform(
        [np.hstack([h, u]) for h, u in zip(hidden, observed, strict=True)])])
    norms = np.linalg.norm(theta, axis=0)
    return float(np.max(np.abs(model.coefficients() * norms[None, :]))) or 1.0


def _refit_integral(model, hidden, observed, times, span):
    """Least squares of the increments of h over ``span`` samples on the integrals of
    the library, on the model's support (coefficients set in place)."""
    span = max(1, min(int(span), min(len(h) for h in hidden) - 1))
    thetas = model.feature_library.transform(
        [np.hstack([h, u]) for h, u in zip(hidden, observed, strict=True)])
    theta = np.vstack([_integrals(np.asarray(a), tk, span)
                       for a, tk in zip(thetas, times, strict=True)])
    target = np.vstack([h[span:] - h[:-span] for h in hidden])
    coef = model.coefficients()
    for k in range(target.shape[1]):
        cols = np.flatnonzero(coef[k])
        if len(cols):
            coef[k, cols] = np.linalg.lstsq(theta[:, cols], target[:, k], rcond=None)[0]
    model.optimizer.coef_ = coef


def _steps(times, n):
    t = np.asarray(times, dtype=float)
    return np.full(n - 1, float(t)) if t.ndim == 0 else np.diff(t)


def _integrals(values, times, span):
    """Trapezoid integrals of ``values`` (n_times, k) over every interval of ``span``
    samples, (n_times - span, k)."""
    dt = _steps(times, len(values))[:, None]
    cum = np.concatenate([np.zeros((1, values.shape[1])),
                          np.cumsum((values[1:] + values[:-1]) / 2 * dt, axis=0)])
    return cum[span:] - cum[:-span]


def _cv_error(theta, target, support):
    """Held-out error (relative to each target's variance) of least squares on support,
    and its standard error across the folds."""
    n = len(target)
    edges = np.linspace(0, n, N_FOLDS + 1).astype(int)
    folds = np.zeros(N_FOLDS)
    for k in range(target.shape[1]):
        cols = np.flatnonzero(support[k])
        scale = n * max(float(np.var(target[:, k])), 1e-300)
        for f, (a, b) in enumerate(zip(edges[:-1], edges[1:], strict=True)):
            train = np.r_[0:a, b:n]
            pred = np.zeros(b - a)
            if len(cols):
                coef, *_ = np.linalg.lstsq(theta[np.ix_(train, cols)], target[train, k],
                                           rcond=None)
                pred = theta[a:b, cols] @ coef
            folds[f] += float(np.sum((target[a:b, k] - pred) ** 2)) / scale
    total = float(folds.sum())
    return total, float(np.std(folds * N_FOLDS, ddof=1) / np.sqrt(N_FOLDS))
