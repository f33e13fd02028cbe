"""Recordings as measured: missing samples, gaps, and several recordings of one system.

A recording is cut into segments that share the law and each get their own hidden
initial values. Rows with a missing value (NaN, in any state or in the time) are
dropped; an infinite value is an error (it is a failed computation or a sensor's
overflow, not a missing sample: replace it with NaN to drop its row). When more than
:data:`WARN_SHARE` of a recording's rows go unused (missing, or in segments too short
to use), a warning says so: the result's ``data_use`` counts them too. A few dropped
rows only make the sampling irregular, which every later step handles on the actual
times. A *gap* is a time step far longer than the
spacing around it (:data:`GAP_FACTOR` times the mean of the
:data:`_NEIGHBOURS` steps on either side): the derivative there cannot be estimated
and a hidden state cannot be carried across it by the data, so the recording is
split. The factor is wide enough that random (Poisson) sample times, whose longest
step in 10^5 samples is about 12 mean steps, are never split. Segments too short to
estimate a derivative and a hidden state's start (:data:`MIN_SEGMENT` samples) are
dropped, each with a note.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np

from . import spikes
from . import validation as val

GAP_FACTOR = 20.0  # a step this many times the local mean step splits a recording
# fewer samples cannot fix a law's parameters and a hidden start: stage one's
# differentiator needs 7, its structure test the law's terms (a degree-2 library with one
# state: 3) and their variation, the refinement two held-out segments of 8 samples
MIN_SEGMENT = val.MIN_TIMES
MIN_PANEL = 8  # shortest recording of a panel (the refinement's shortest segment)
_NEIGHBOURS = 16  # steps on either side that set the local spacing
GAPS = ("split", "raise")
OUTLIERS = ("discount", "keep")
WARN_SHARE = 0.1  # a recording losing more than this share of its rows gets a warning


@dataclass(frozen=True)
class DataUse:
    """How the data were used: recordings given, segments and samples used, rows with
    missing values dropped, one sentence per segment that was too short to use, and
    where each segment used came from: (recording, first row, last row), in the order
    of the result's trajectories; and the samples discounted as isolated spikes, each as
    (recording, time) (:mod:`latentsindy._core.spikes`: their values were replaced by
    their neighbours' curve)."""

    recordings: int
    segments: int
    samples: int
    missing_rows: int
    dropped: tuple[str, ...] = ()
    sources: tuple[tuple[int, int, int], ...] = ()
    discounted: tuple[tuple[int, float], ...] = ()

    def reordered(self, order) -> DataUse:
        """The same, with the segments in ``order``."""
        return replace(self, sources=tuple(self.sources[i] for i in order))

    def sentence(self) -> str:
        rec = f"{self.recordings} recording{'s' if self.recordings > 1 else ''}"
        text = (f"{rec}, {self.segments} segment{'s' if self.segments > 1 else ''}, "
                f"{self.samples} samples used")
        if self.missing_rows:
            text += f" ({self.missing_rows} rows with missing values dropped)"
        if self.discounted:
            shown = ", ".join(f"t={t:g}" + (f" (recording {k})" if self.recordings > 1 else "")
                              for k, t in self.discounted[:3])
            more = ", ..." if len(self.discounted) > 3 else ""
            text += (f"; {len(self.discounted)} isolated spike(s) discounted ({shown}{more}): "
                     "replaced by their neighbours' curve")
        return text


def split(x, t, *, gaps: str = "split", outliers: str = "discount", what: str = "x_observed",
          _floor: int = MIN_SEGMENT):
    """Validate recordings and cut them at missing values and gaps.

    Parameters
    ----------
    x : array (n_times, n_states) or list of such arrays (NaN allowed)
    t : spacing, times, or a list of either (one per recording)
    gaps : ``"split"`` (default) or ``"raise"`` (refuse missing values and gaps)
    outliers : ``"discount"`` (default: isolated spikes replaced by their neighbours'
        curve and listed, :mod:`.spikes`) or ``"keep"``

    Pieces shorter than :data:`MIN_SEGMENT` samples are dropped with a note, unless
    none is that long: then every piece of :data:`MIN_PANEL` samples or more is used
    (a panel of short recordings, subjects, batches or trials, or one short
    recording: the law is shared, each piece adds its own hidden start; stage two
    searches without stage one and the result says so).

    Returns
    -------
    segments : list of (n_k, n_states) finite arrays
    times : list of (n_k,) strictly increasing times
    use : :class:`DataUse`
    """
    if gaps not in GAPS:
        raise ValueError(f"gaps must be one of {GAPS}; got {gaps!r}.")
    if outliers not in OUTLIERS:
        raise ValueError(f"outliers must be one of {OUTLIERS}; got {outliers!r}.")
    recordings = _recordings(x, what, t)
    times = _times(t, recordings)
    segments, seg_times, sources, dropped, missing = [], [], [], [], 0
    discounted, short = [], []
    unused_notes = []  # warned about once something is left to use
    for k, (xk, tk) in enumerate(zip(recordings, times, strict=True)):
        name = f"{what}[{k}]" if len(recordings) > 1 else what
        _check_infinite(xk, tk, name)
        bad = ~np.all(np.isfinite(xk), axis=1) | ~np.isfinite(tk)
        _check_columns(xk, name)
        if bad.any() and gaps == "raise":
            raise ValueError(
                f"{name} has {int(bad.sum())} row(s) with a NaN value or time "
                f"(first at row {int(np.argmax(bad))}); with gaps='raise' they are refused. Use "
                "the default gaps='split' to drop them and split the recording where they "
                "leave a gap.")
        if bad.all():
            raise ValueError(
                f"Every row of {name} ({len(bad)} rows) has a NaN value in some "
                "state or in its time, and a row with any missing value is dropped: nothing "
                "is left. States measured at different times need a common time grid "
                "(interpolate the slower one), or pass only the states measured together.")
        t_name = "t" if len(recordings) == 1 else f"t[{k}]"
        val._one_times(tk, len(tk), t_name, missing=bad)
        rows = np.flatnonzero(~bad)
        missing += int(bad.sum())
        cuts = gap_steps(tk[rows])
        if len(cuts) and gaps == "raise":
            i = int(cuts[0])
            raise ValueError(
                f"{name} has {len(cuts)} gap(s): a time step more than {GAP_FACTOR:g} times the "
                f"spacing around it (first from t={tk[rows[i]]:g} to t={tk[rows[i + 1]]:g}); "
                "with gaps='raise' they are refused. Use the default gaps='split' to treat "
                "the pieces as segments of one system.")
        unused, spiked = int(bad.sum()), 0
        for piece in np.split(rows, cuts + 1):
            if len(piece) < _floor:
                unused += len(piece)
                short.append(len(piece))
                dropped.append(f"a segment of {name} with {len(piece)} samples (t={tk[piece[0]]:g} "
                               f"to {tk[piece[-1]]:g}) was dropped: fewer than {_floor} "
                               "samples between gaps")
                continue
            piece_t = np.asarray(tk[piece], dtype=float)
            values = xk[piece]
            if outliers == "discount":
                hit, values = spikes.discount(values, piece_t)
                discounted += [(k, float(v)) for v in piece_t[hit]]
                spiked += int(hit.sum())
            segments.append(values)
            sources.append((k, int(piece[0]), int(piece[-1])))
            seg_times.append(piece_t)
        if unused + spiked > WARN_SHARE * len(xk):
            unused_notes.append(
                f"{unused + spiked} of the {len(xk)} rows of {name} "
                f"({(unused + spiked) / len(xk):.0%}) are not used as measured: "
                f"{int(bad.sum())} have a missing value, {unused - int(bad.sum())} lie in "
                f"segments shorter than {_floor} samples between gaps and {spiked} were "
                "discounted as isolated spikes (see the result's data_use). Check the "
                "recording if that is not what you expect.")
    usable = [n for n in short if n >= MIN_PANEL]
    if not segments and _floor > MIN_PANEL and usable:
        return split(x, t, gaps=gaps, outliers=outliers, what=what, _floor=MIN_PANEL)
    if not segments:
        raise ValueError(
            f"No part of {what} is long enough to use: at least {MIN_PANEL} samples without "
            f"a gap are needed in a recording ({MIN_SEGMENT} for stage one; a law's "
            "parameters and each recording's hidden start need more samples than they "
            "are: twice as many give an answer to check, 8 per cycle of the fastest "
            "oscillation over a few cycles a confident law, hundreds of samples a better "
            f"one), and {'; '.join(dropped)}.")
    for note in unused_notes:
        warnings.warn(note, UserWarning, stacklevel=4)  # at the discover_hidden call
    use = DataUse(len(recordings), len(segments), int(sum(len(s) for s in segments)),
                  missing, tuple(dropped), tuple(sources), tuple(discounted))
    return segments, seg_times, use


def gap_steps(t) -> np.ndarray:
    """Indices ``i`` of the steps ``t[i] -> t[i + 1]`` that are gaps."""
    steps = np.diff(np.asarray(t, dtype=float))
    n = len(steps)
    if n < 3:
        return np.zeros(0, dtype=int)
    csum = np.concatenate([[0.0], np.cumsum(steps)])
    idx = np.arange(n)
    lo = np.maximum(idx - _NEIGHBOURS, 0)
    hi = np.minimum(idx + _NEIGHBOURS + 1, n)
    around = (csum[hi] - csum[lo] - steps) / np.maximum(hi - lo - 1, 1)
    return np.flatnonzero(steps > GAP_FACTOR * around)


def _recordings(x, what, t=None):
    if isinstance(x, list | tuple) and len(x) > 0 and np.ndim(x[0]) <= 1:
        if _several_times(t, len(x)) and all(np.ndim(xi) == 1 for xi in x):
            x = [np.asarray(xi)[:, None] for xi in x]  # single-state recordings
        elif val._ragged(x) and all(np.ndim(xi) == 1 for xi in x):
            raise ValueError(
                f"{what} is a list of {len(x)} 1-D arrays of different lengths "
                f"{[len(xi) for xi in x][:6]}: read as one series, its rows differ. For "
                "several recordings of one state pass t as a list of their times as well, "
                "or give each recording the shape (n_times, 1).")
        else:
            x = np.asarray(x, dtype=object if val._ragged(x) else None)  # one series
    if isinstance(x, list | tuple):
        if len(x) == 0:
            raise ValueError(f"{what} is an empty list; pass at least one recording.")
        recs = [val.numeric_2d(xi, f"{what}[{k}]") for k, xi in enumerate(x)]
    else:
        recs = [val.numeric_2d(x, what)]
    n_states = {r.shape[1] for r in recs}
    if len(n_states) > 1:
        raise ValueError(f"All recordings in {what} must have the same number of states; got "
                         f"{sorted(n_states)}.")
    return recs


def _several_times(t, n):
    """Whether ``t`` is a list of ``n`` > 1 arrays of times (one per recording)."""
    return (isinstance(t, list | tuple) and n > 1 and len(t) == n
            and all(np.ndim(tk) == 1 for tk in t))


def _times(t, recordings):
    n = len(recordings)
    if n == 1 and _several_times(t, len(t) if isinstance(t, list | tuple) else 0):
        raise ValueError(f"t is a list of {len(t)} arrays of times but x is one recording; "
                         "pass x as a list of as many recordings, or t as one array.")
    if isinstance(t, list | tuple) and n > 1:
        if len(t) != n:
            raise ValueError(f"t is a list of {len(t)} entries but x has {n} recordings.")
        items = list(t)
    else:
        if isinstance(t, list | tuple) and len(t) == 1 and np.ndim(t[0]) >= 1:
            t = t[0]
        items = [t] * n
    out = []
    for k, (tk, xk) in enumerate(zip(items, recordings, strict=True)):
        name = "t" if n == 1 else f"t[{k}]"
        if tk is None:
            raise TypeError(f"{name} is required: a sample spacing (float) or an array of times.")
        if np.ndim(tk) == 0:
            out.append(val._one_times(tk, xk.shape[0], name))
            continue
        arr = np.asarray(tk)
        if arr.dtype.kind in val._KINDS or arr.ndim != 1 or arr.shape[0] != xk.shape[0]:
            val._one_times(tk, xk.shape[0], name)  # raises the boundary's message
        out.append(np.asarray(arr, dtype=float))
    return out


def _check_infinite(x, t, name):
    rows = np.flatnonzero(np.isinf(x).any(axis=1) | np.isinf(np.asarray(t, dtype=float)))
    if len(rows):
        shown = ", ".join(str(r) for r in rows[:5]) + (", ..." if len(rows) > 5 else "")
        raise ValueError(
            f"{name} has {len(rows)} row(s) with an infinite value or time (rows {shown}). "
            "An infinite value is not a missing sample but a failed computation or an "
            "overflow; replace it with NaN to drop its row (a missing sample), or fix it.")


def _check_columns(x, name):
    empty = np.flatnonzero(~np.any(np.isfinite(x), axis=0))
    if len(empty):
        raise ValueError(f"{name} has state column(s) {empty.tolist()} with no finite value; "
                         "drop those columns (a state never measured is a hidden one).")
