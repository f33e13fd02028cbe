"""Stage two: time-varying coefficients become hidden states of a closed system."""

from __future__ import annotations

import copy

import numpy as np
import pysindy as ps
import sympy as sp

from . import _validation as val
from ._closure import fit_closure
from ._derivatives import AdaptiveSavitzkyGolay
from ._discovery import HiddenDiscovery
from ._estimator import DynamicSINDy
from ._library import check_library, feature_expressions, fit_library, state_symbols

VARIATION_SIGMAS = 3.0  # variation must exceed this many posterior std ...
VARIATION_RELATIVE = 0.05  # ... and this fraction of the coefficient's mean size


def discover_hidden(x_observed, library=None, *, t, feature_names=None, hidden_terms=None,
                    hidden_names=None, closure_library=None, generator="timevae",
                    generator_options=None, training=None, differentiation_method=None,
                    support=None, n_samples=64, seed=0, verbose=True) -> HiddenDiscovery:
    """Infer hidden variables and a closed, autonomous ODE from partial observations.

    Stage one fits time-varying coefficients Xi(t) (:class:`DynamicSINDy`); each
    coefficient series that varies in time becomes a hidden state h in physical units,
    so the observed equations read ``Theta(x) Xi`` with h substituted (Lotka-Volterra
    with only the prey observed: ``xdot = x h`` with ``h = alpha - beta y``). pysindy
    then finds equations for the hidden states over observed plus hidden states.

    Parameters
    ----------
    x_observed : array (n_times, n_observed) or list of such arrays
    library : pysindy feature library, optional
        Candidate functions for the observed equations (default polynomials of degree 2).
    t : float, array or list of arrays
        Sample spacing or times.
    feature_names : list of str, optional
        Names of the observed states (default ``x0, x1, ...``).
    hidden_terms : list of (state, feature), optional
        Which coefficients are hidden states. By default a coefficient is hidden when
        its variation over time exceeds 3 posterior standard deviations and 5% of its
        mean size; the others become constants (their time average).
    hidden_names : list of str, optional
        Names of the hidden states (default ``h0, h1, ...``).
    closure_library : pysindy feature library, optional
        Candidates for the hidden equations (default polynomials of degree 2).
    generator, generator_options, training, differentiation_method, support
        Passed to :class:`DynamicSINDy`.
    n_samples : int
        Posterior samples for the uncertainty band.
    seed : int
    verbose : bool

    Returns
    -------
    HiddenDiscovery
    """
    trajs = val.as_trajectories(x_observed, "x_observed")
    times = val.as_times(t, trajs)
    names = val.check_feature_names(feature_names, trajs[0].shape[1])
    closure_library = (ps.PolynomialLibrary(degree=2) if closure_library is None
                       else closure_library)
    if not isinstance(closure_library, ps.feature_library.base.BaseFeatureLibrary):
        raise TypeError("closure_library must be a pysindy feature library; got "
                        f"{type(closure_library).__name__}.")
    val.check_positive(n_samples, "n_samples", integer=True)
    _, features = fit_library(check_library(library), trajs[:1], names)
    _check_hidden_request(hidden_terms, hidden_names, names, features)

    # Stage one, one model per trajectory: hidden states differ between trajectories.
    # Later trajectories reuse the first one's support so the equations are shared.
    fits, coefs = [], []
    for k, (x, tk) in enumerate(zip(trajs, times, strict=True)):
        model = DynamicSINDy(library, generator=generator, generator_options=generator_options,
                             training=training, differentiation_method=differentiation_method,
                             support=support if k == 0 else fits[0].support_,
                             device="cpu", verbose=verbose, seed=seed)
        fits.append(model.fit(x, tk, feature_names=names))
        coefs.append(model.coefficients(n_samples=n_samples))
    first = coefs[0]
    hidden_pairs = _hidden_pairs(coefs, hidden_terms)
    n_hidden = len(hidden_pairs)
    hidden_names = _hidden_names(hidden_names, n_hidden, names, hidden_pairs)
    if n_hidden == 0:
        raise ValueError(
            "No coefficient varies in time beyond its uncertainty, so there is no hidden "
            f"variable to discover (active terms: {first.active_terms()}). If one should vary, "
            "name it with hidden_terms=[(state, feature)].")

    # Observed equations: Theta(x) Xi with constants averaged and hidden states substituted
    hs = state_symbols(hidden_names)
    feats = feature_expressions(fits[0].library_, first.feature_names, names)
    constants = np.mean([c.mean.mean(axis=0) for c in coefs], axis=0) * first.support
    rhs = {}
    for i, s in enumerate(names):
        expr = sp.Integer(0)
        for j, f in enumerate(feats):
            if (s, first.feature_names[j]) in hidden_pairs:
                expr += hs[hidden_pairs.index((s, first.feature_names[j]))] * f
            elif constants[i, j] != 0:
                expr += sp.Float(float(constants[i, j])) * f
        rhs[s] = sp.expand(expr)

    # Closure: pysindy on the hidden states, observed states as inputs
    index = [(first.state_names.index(s), first.feature_names.index(f)) for s, f in hidden_pairs]
    hidden = [np.stack([c.mean[:, i, j] for i, j in index], axis=1) for c in coefs]
    diff = AdaptiveSavitzkyGolay()
    hidden_dot, smooth_obs, spans = [], [], []
    for h, x, tk, m in zip(hidden, trajs, times, fits, strict=True):
        hidden_dot.append(diff(h, tk))
        smooth, span = _smoothed(m, x, tk)
        smooth_obs.append(smooth)
        spans.append(span)
    sindy, table = fit_closure(hidden, hidden_dot, smooth_obs, times, closure_library,
                               hidden_names, names, span=max(spans))
    closure_feats = feature_expressions(sindy.feature_library, sindy.get_feature_names(),
                                        list(hidden_names) + list(names))
    for k, h in enumerate(hidden_names):
        row = sindy.coefficients()[k]
        rhs[h] = sp.expand(sum((sp.Float(float(c)) * f for c, f in zip(row, closure_feats,
                                                                         strict=True) if c != 0),
                               sp.Integer(0)))
    stds = [np.stack([c.std[:, i, j] for i, j in index], axis=1) for c in coefs]
    return HiddenDiscovery.build(
        times=times, observed=trajs, hidden=hidden, hidden_std=stds,
        initial_state=np.concatenate([smooth_obs[0][0], hidden[0][0]]),
        observed_names=tuple(names), hidden_names=tuple(hidden_names),
        hidden_terms=tuple(hidden_pairs), rhs=rhs, sindy=sindy, coefficients=first,
        closure_candidates=table,
    )


def _smoothed(model, x, t):
    """The observed states as the stage-one differentiator smoothed them (less noise in
    the closure library), or the raw data when the method keeps no smoothed copy; and
    the differentiator's resolution in samples (its widest smoothing window, or 1)."""
    method = copy.deepcopy(model.differentiation_method) or AdaptiveSavitzkyGolay()
    method(x, t)
    smooth = getattr(method, "smoothed_x_", None)
    span = int(max(getattr(method, "windows_", None) or [1]))
    if smooth is None or np.shape(smooth) != x.shape:
        return x, span
    return np.asarray(smooth), span


def _check_hidden_request(hidden_terms, hidden_names, states, features):
    """Validate hidden_terms / hidden_names before any training."""
    if hidden_terms is not None:
        pairs = []
        for p in hidden_terms:
            if (not isinstance(p, list | tuple) or len(p) != 2 or p[0] not in states
                    or p[1] not in features):
                raise ValueError(
                    f"hidden_terms entries must be (state, feature) pairs with state in "
                    f"{list(states)} and feature in {list(features)}; got {p!r}.")
            pairs.append(tuple(p))
        if len(set(pairs)) != len(pairs):
            raise ValueError(f"hidden_terms has duplicates: {pairs}.")
        if hidden_names is not None and len(hidden_names) != len(pairs):
            raise ValueError(f"hidden_names has {len(hidden_names)} name(s) but "
                             f"{len(pairs)} hidden state(s) were requested in hidden_terms.")
    if hidden_names is not None:
        names = val.check_feature_names(hidden_names, len(hidden_names), "hidden_names")
        clash = set(names) & set(states)
        if clash:
            raise ValueError(f"hidden_names {sorted(clash)} clash with the observed state names.")


def _hidden_pairs(coefs, hidden_terms):
    first = coefs[0]
    if hidden_terms is not None:
        pairs = [tuple(p) for p in hidden_terms]
        active = set(first.active_terms())
        for p in pairs:
            if p not in active:
                raise ValueError(f"hidden term {p!r} was removed by the sparsity stage "
                                 f"(active terms: {sorted(active)}); fix it with support=.")
        return pairs
    pairs = []
    for s, f in first.active_terms():
        if all(_varies(c.term(s, f), c.term_std(s, f)) for c in coefs):
            pairs.append((s, f))
    return pairs


def _varies(mean, std):
    variation = float(np.std(mean))
    return (variation > VARIATION_SIGMAS * float(np.mean(std))
            and variation > VARIATION_RELATIVE * float(np.mean(np.abs(mean))))


def _hidden_names(names, n_hidden, observed, pairs):
    if names is None:
        names = [f"h{k}" for k in range(n_hidden)]
    if len(names) != n_hidden:
        raise ValueError(f"hidden_names has {len(names)} name(s) but {n_hidden} hidden state(s) "
                         f"were found: coefficients {pairs}. Pass {n_hidden} names, or choose "
                         "the hidden states with hidden_terms=[(state, feature), ...].")
    return list(names)
