"""Building stage two's :class:`.context.Context`: the data as stage one smoothed them
(or as measured), the library on them, the noise level and the hidden series' knots."""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from .._core import validation as val
from .._core.derivatives import AdaptiveSavitzkyGolay, marginal_noise, window_capped
from .._core.library import feature_expressions
from .._core.timing import timed
from .context import Context, floor_noise


@timed("smoothing")
def build(model, trajs, times, names, first, closure_library, support, threshold):
    """The context of one discovery: the data, stage one's smoothing of them, the library
    on the smoothed states, the noise level and the hidden series' knot spacing."""
    smoothed, spans, capped = [], [], []
    for x, tk in zip(trajs, times, strict=True):
        sm, span, cap = smoothed_states(model, x, tk)
        smoothed.append(sm)
        spans.append(span)
        capped.append(cap)
    library = model.library_
    thetas = [np.asarray(a, dtype=float) for a in library.transform(smoothed)]
    sigma = floor_noise(marginal_noise(list(trajs), list(times)), trajs)
    span = int(max(spans))
    return Context(tuple(names), tuple(first.feature_names),
                   tuple(feature_expressions(library, first.feature_names, names)),
                   [np.asarray(tk, float) for tk in times], [np.asarray(x) for x in trajs],
                   smoothed, thetas, sigma, knot_spacing(spans, capped, times), span,
                   val.free_rows(support, names), threshold, closure_library)


def knot_spacing(spans, capped, times, max_knots=400):
    """Knot spacing of the hidden series per trajectory, in its mean sample steps.

    Knots sit every half differentiator window in time: the finest scale the data
    resolve. With several segments that is the narrowest window (in time) among the
    segments whose window the noise chose: a segment on a slow stretch of the dynamics
    gets a wide window that would blur the others, while a short segment's window is
    limited by its length (``capped``), which says nothing about the dynamics. Every
    series gets at most ``max_knots`` knots over the longest one's duration (a hidden
    state of an ODE does not need more, and the smoother's cost grows with them).
    """
    steps = [(t[-1] - t[0]) / max(len(t) - 1, 1) for t in times]
    widths = [s * w for s, w, c in zip(steps, spans, capped, strict=True) if not c]
    if not widths:
        widths = [s * w for s, w in zip(steps, spans, strict=True)]
    longest = int(np.argmax([len(t) for t in times]))
    coarsest = -(-len(times[longest]) // max_knots) * steps[longest]
    spacing = max(min(widths) / 2, coarsest)
    # floor with a little slack: one uniform series gives exactly span // 2 samples
    return [int(max(1, np.floor(spacing / s + 1e-6))) for s in steps]


def smoothed_states(model, x, t):
    """The observed states as the stage-one differentiator smoothed them (less noise in
    the closure library), or the raw data when the method keeps no smoothed copy; the
    differentiator's resolution in samples (its widest smoothing window, or 1); and
    whether that window was limited by the series' length rather than its noise."""
    method = copy.deepcopy(model.differentiation_method) or AdaptiveSavitzkyGolay()
    method(x, t)
    smooth = getattr(method, "smoothed_x_", None)
    span = int(max(getattr(method, "windows_", None) or [1]))
    capped = (isinstance(method, AdaptiveSavitzkyGolay)
              and window_capped(span, len(x), method.max_window))
    if smooth is None or np.shape(smooth) != x.shape:
        return x, span, capped
    return np.asarray(smooth), span, capped


def as_measured(ctx, library):
    """``ctx`` on the data as measured: where stage one saw no law its differentiator's
    smoothing (a window spanning much of a cycle) flattens the states, so the library
    is evaluated on the samples themselves and the hidden series get a knot at every
    sample (the smoother's curvature penalty, not the knots, sets their smoothness)."""
    thetas = [np.asarray(a, dtype=float) for a in library.transform(ctx.observed)]
    return dataclasses.replace(ctx, smoothed=[np.asarray(x) for x in ctx.observed],
                               thetas=thetas, spacing=[1] * len(ctx.observed), span=1)


def bare(library, trajs, times, names, features, closure_library, support, threshold):
    """A context without stage one (a panel): the data as measured, the library on them
    (:func:`as_measured`), the noise pooled over the recordings."""
    observed = [np.asarray(x, float) for x in trajs]
    sigma = floor_noise(marginal_noise(observed, list(times)), observed)
    ctx = Context(tuple(names), tuple(features),
                  tuple(feature_expressions(library, list(features), names)),
                  [np.asarray(tk, float) for tk in times], observed, observed, [], sigma,
                  [1] * len(observed), 1, val.free_rows(support, names), threshold,
                  closure_library)
    return as_measured(ctx, library)
