"""A panel's recordings integrated side by side.

Each recording is a :class:`~.shooting.Group` of segments on one grid. Integrated
group by group, a panel of short recordings costs one call of the integrator per
recording for every evaluation, each call mostly Python overhead for a segment or two:
20 recordings of 11 samples made 35,000 calls in one discovery, over 80% of its time.
:func:`run_groups` integrates the groups in a few :class:`Batch` es instead; every
segment keeps its own group's grid (shorter grids padded with steps of length zero),
so the arithmetic of each segment is what it was group by group.
"""

from __future__ import annotations

import numpy as np
import torch

from .shooting import Batch, BlowUp

GROWTH = 2  # within a batch, the longest grid has at most this many times the points


def make_batches(groups) -> list[Batch] | None:
    """The groups in batches of similar grid length (None for a single group: it is
    integrated as it is)."""
    if len(groups) < 2:
        return None
    order = sorted(range(len(groups)), key=lambda i: len(groups[i].grid))
    buckets = [[order[0]]]
    for i in order[1:]:
        if len(groups[i].grid) > GROWTH * len(groups[buckets[-1][0]].grid):
            buckets.append([])
        buckets[-1].append(i)
    return [_batch(groups, bucket) for bucket in buckets]


def _batch(groups, members) -> Batch:
    n_rows = sum(groups[i].n_segments for i in members)
    n_grid = max(len(groups[i].grid) for i in members)
    n_pos = max(groups[i].positions.shape[1] for i in members)
    grid, positions = np.zeros((n_rows, n_grid)), np.zeros((n_rows, n_pos))
    lengths, out, row = np.zeros(n_rows, dtype=np.int64), [], 0
    for i in members:
        g = groups[i]
        own, k, m = g.grid.cpu().numpy(), g.n_segments, g.positions.shape[1]
        grid[row:row + k, :len(own)] = own
        grid[row:row + k, len(own):] = own[-1]  # steps of length zero
        positions[row:row + k, :m] = g.positions.cpu().numpy()
        lengths[row:row + k] = len(own)
        out.append((i, row, k, m))
        row += k
    on = groups[members[0]].grid.device
    as_t = lambda a: torch.as_tensor(a, dtype=torch.float64, device=on)  # noqa: E731
    return Batch(out, as_t(grid), as_t(positions), lengths)


def run_groups(integrator, coef, starts, groups, batches, sensitivities=True,
               components=None, blow_ups=False, as_numpy=False):
    """``(group, its segments, Integrator.run's output for them)`` for every group, in
    the groups' order, integrated batch by batch (``batches`` from
    :func:`make_batches`; None: group by group). ``blow_ups``: a batch that blows up is
    integrated again group by group, and a group that blows up on its own comes with
    the output None (else :class:`BlowUp` is raised). ``as_numpy``: the outputs as
    numpy arrays, not tensors."""
    def own(g):
        segs = np.arange(g.first, g.first + g.n_segments)
        return segs, integrator.run(coef, starts[segs], g, sensitivities, components, as_numpy)

    if batches is None:
        for g in groups:
            yield (g, *own(g))
        return
    outputs = {}
    for b in batches:
        rows = np.concatenate([np.arange(groups[i].first, groups[i].first + k)
                               for i, _, k, _ in b.members])
        try:
            out = integrator.run(coef, starts[rows], b, sensitivities, components, as_numpy)
        except BlowUp:
            if not blow_ups:
                raise
            for i, *_ in b.members:
                try:
                    outputs[i] = own(groups[i])[1]
                except BlowUp:
                    outputs[i] = None
            continue
        for i, first, k, m in b.members:
            outputs[i] = _rows(out, first, k, m)
    for i, g in enumerate(groups):
        yield g, np.arange(g.first, g.first + g.n_segments), outputs[i]


def _rows(out, first, k, m):
    """One group's part of a batch's output: its rows, its first ``m`` positions."""
    values, ends = out
    if isinstance(values, tuple):
        return (tuple(a[first:first + k, :m] for a in values),
                tuple(a[first:first + k] for a in ends))
    return values[first:first + k, :m], ends[first:first + k]
