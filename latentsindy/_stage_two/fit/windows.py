"""The judged part of a long recording: windows spread over it.

Term selection refits a closed system for every move it tries, and the held-out score
refits it once per fold; each refit integrates every segment, so on a long recording
these dominate a discovery and grow with its length (prey-only Lotka-Volterra at 20,000
samples: 7.5 of 16.6 s on one core, against 1.3 of 4.1 s at 2,000). Beyond
``LONG`` samples they are made on ``WINDOWS`` stretches of whole segments spread
evenly over the data, about ``JUDGED`` samples in all (:func:`judged_part`). So are the
hypotheses' first fits, which decide which of them contend (:func:`.verdict.first_fit`).
Only the system chosen among them all is fitted on every sample
(:func:`.verdict.on_whole`: from its starts on the windows and the guesses elsewhere);
one that does not join there is passed over (prey-only LV at 20,000 samples, draw 0,
one process: the first fits on every sample took 2.5 of 11.2 s, and the windows' own
refits of them before selection 0.6 s more; draw 1, with every contender fitted on
every sample after selection, those fits 1.3 of 8.3 s). A restatement of the chosen
system is judged on the windows too, and fitted on every sample only where it is chosen.
``JUDGED`` is twice the 2,000 samples on which
every benchmark family is judged in full: evidence for a term grows with the samples,
and by then it decides. Windows, rather than one stretch, so that every part of a
recording that changes regime over time is seen; several periods each, so that a
hidden state is seen at work. ``LONG`` is four times ``JUDGED``, so the windows hold
at most a quarter of the data: at 10,000 samples (windows of 40%) the selection on
them made as many moves as on the whole and the refits on every sample cost more
than was saved (5 of 8 families slower, the damped Duffing 8.4 -> 13.6 s), where at
20,000 it saved (prey-only LV 12.7 -> 8.7 s, the Duffing 26.0 -> 18.8 s, the same
structures).
"""

from __future__ import annotations

import copy

import numpy as np

from .batches import make_batches
from .shooting import Group
from .whiten import carry_over

JUDGED = 4000  # samples, about, on which a long recording is judged
WINDOWS = 4
LONG = 4 * JUDGED  # samples beyond which a recording is judged on windows


def judged_part(problem):
    """The problem restricted to ``WINDOWS`` stretches of whole segments, about
    ``JUDGED / WINDOWS`` samples each, starting at samples evenly spread over the data;
    None when it has at most ``LONG`` samples (judged whole), or when the stretches
    would hold half its samples or more. A stretch is counted in samples, not segments,
    so that a sparsely sampled stretch (or recording) is not taken for a dense one; a
    stretch that crosses from one recording into the next is cut in two there. The
    part's ``rows`` are its segments' indices in ``problem`` (its starts are
    ``starts[part.rows]``)."""
    counts = np.concatenate([g.mask.numpy().sum(axis=1) for g in problem.groups])
    total = int(counts.sum())
    if total <= LONG:
        return None
    ends = np.cumsum(counts)  # samples up to each segment's end
    each = JUDGED / WINDOWS
    chosen = np.zeros(len(counts), dtype=bool)
    for sample in np.linspace(0, total - each, WINDOWS):
        first = int(np.searchsorted(ends, sample, side="right"))  # the segment holding it
        last = int(np.searchsorted(ends, ends[first] - counts[first] + each))
        chosen[first:last + 1] = True
    if 2 * int(counts[chosen].sum()) > total:
        return None
    return _part(problem, chosen)


def _part(problem, chosen):
    """``problem`` on the segments marked in ``chosen``: every run of consecutive chosen
    segments of one recording becomes a recording of its own (the same segments, grids,
    scales and noise model; its own AR(1) carry-over and batches)."""
    groups, times, observed, rows = [], [], [], []
    for g in problem.groups:
        marks = np.r_[False, chosen[g.first:g.first + g.n_segments], False].astype(int)
        edges = np.flatnonzero(np.diff(marks))
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            # a run holds samples: it starts at a segment holding the sample a window
            # starts from, or at a recording's first segment (which holds its first)
            index = g.sample_index[a:b]
            lo = int(index[index >= 0].min())
            hi = int(index.max()) + 1
            t, x = problem.times[g.trajectory], problem.observed[g.trajectory]
            groups.append(Group(len(groups), len(rows), b - a, g.grid, g.positions[a:b],
                                g.observed[a:b], g.mask[a:b],
                                np.where(index >= 0, index - lo, -1), g.starts[a:b]))
            times.append(t[lo:hi])
            observed.append(x[lo:hi])
            rows.extend(range(g.first + a, g.first + b))
    part = copy.copy(problem)
    part.groups, part.times, part.observed = groups, times, observed
    part.batches = make_batches(groups)
    part.carry = None if problem.carry is None else carry_over(groups, problem.phi,
                                                               problem.dt)
    part.n_segments = len(rows)
    part.rows = np.asarray(rows, dtype=np.int64)
    part.initial_starts = problem.initial_starts[part.rows]
    part.n_data = int(sum(int(g.mask.sum()) for g in groups)) * problem.n_obs
    return part
