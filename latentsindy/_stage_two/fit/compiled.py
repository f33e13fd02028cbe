"""Stage two's Runge-Kutta on polynomial fields, compiled: the whole integration in one call.

The refinement and the term selection integrate thousands of small batches (a few
segments of a few states with their sensitivities), each of hundreds of Runge-Kutta
steps. Written in numpy (:func:`.shooting.rk4`), every step is a few dozen array
operations whose fixed cost (a microsecond or more each) is most of the time: on the
Hindmarsh-Rose neuron, 1.3 million field evaluations at about 65 microseconds each,
half of a discovery's work. Here the same steps run as one compiled loop (numba), so
an evaluation costs its arithmetic.

The arithmetic is :func:`.shooting.rk4`'s (in numpy, its reference here) with the field of
:meth:`.shooting.Integrator._polynomial_field`: the same monomials (powers by repeated
products, multiplied state by state), the same stages in the same order. Only the
matrix products are summed in their own order (left to right, skipping the table's
zeros) where numpy calls the BLAS: the states agree with numpy's to rounding (a test
holds them to 1e-13 of their scale), not to the bit.

A state that leaves ``bound`` (or is not finite) at any stage stops the integration:
the caller raises :class:`.shooting.BlowUp`, as the numpy field does.
"""

from __future__ import annotations

import threading

import numpy as np
from numba import njit

_ONE_THIRD = 1 / 3
# the trajectories are written into a buffer kept from call to call (per thread), up to
# this many values an array (64 MiB): memory the process has touched before. A fresh
# array of a few megabytes is new pages, and filling them (page faults, zeroing) cost
# more than the integration itself: on the Hindmarsh-Rose neuron's batches (4 states,
# 25 columns, 111 segments, 136 steps: 12 MB each) 2 of 3 seconds on 120 calls
WORKSPACE_LIMIT = 1 << 23
_workspace = threading.local()


def run(integrator, coef, y0, group, sensitivities, components, hermite_table, cache):
    """:meth:`.shooting.Integrator.run`'s values and segment ends (numpy arrays) for a
    polynomial field on the CPU: :func:`states`, then the compiled interpolation (the
    same products and sums as :func:`.shooting._hermite`); None where a state left the
    integrator's bound."""
    n, k = y0.shape[1], y0.shape[0]
    start = with_sensitivities(integrator, y0) if sensitivities else y0
    z, dz, inside = states(integrator, coef, start, group, sensitivities, cache,
                           reuse=True)
    if not inside:
        return None
    rows, _, *weights = hermite_table
    values = hermite(z, dz, rows, *weights, n if components is None else components)
    values = values.reshape(k, group.positions.shape[1], *values.shape[1:])
    ends = np.transpose(z[-1], (2, 0, 1)).copy()  # z may be the workspace: a copy
    if not sensitivities:
        values, ends = values[..., 0], ends[..., 0]
    return values, ends


def with_sensitivities(integrator, y0):
    """The starts ``y0`` (K, n) with their sensitivities at the start (K, n, 1 + n +
    free coefficients): each state's own start 1, everything else 0."""
    k, n = y0.shape
    return np.concatenate([y0[..., None], np.broadcast_to(np.eye(n), (k, n, n)),
                           np.zeros((k, n, len(integrator.rows)))], -1)


def states(integrator, coef, start, group, sensitivities, cache=None, reuse=False):
    """:func:`.shooting.rk4` of ``integrator``'s polynomial field (with its
    sensitivities from ``start`` (K, n, W), or of the states ``start`` (K, n) alone)
    as one compiled loop: the states and slopes (G, n, W, K), the segments last (W = 1
    without sensitivities; ``cache``: a dict that keeps the steps, or None), and
    whether every state stayed within the integrator's bound. With ``reuse`` the
    states and slopes are views of this thread's workspace, valid until its next call
    with ``reuse``."""
    key = ("compiled", len(start))
    steps = None if cache is None else cache.get(key)
    if steps is None:
        steps = np.diff(np.asarray(group.grid.tolist()), axis=-1)
        steps = np.ascontiguousarray(np.broadcast_to(
            steps[:, None] if steps.ndim == 1 else steps.T, (len(steps.T), len(start))))
        if cache is not None:
            cache[key] = steps
    fm, n = integrator.features, start.shape[1]
    if sensitivities:
        z0 = np.transpose(start, (1, 2, 0))
    else:
        z0 = start.T[:, None]
    table = polynomial_table(fm.values_table, fm._flat_gradients, coef, integrator.rows,
                             integrator.cols, sensitivities)
    z, dz = _outputs((len(steps) + 1, *z0.shape), reuse)
    inside = integrate(np.ascontiguousarray(z0), steps, fm.basis, fm.degree, *table, n,
                       float(integrator.bound), z, dz)
    return z, dz, inside


def _outputs(shape, reuse, slot="buffer"):
    """Two arrays of ``shape`` for the states and slopes: views of this thread's
    workspace ``slot`` with ``reuse`` (grown as needed, up to ``WORKSPACE_LIMIT`` values
    each), else new."""
    size = int(np.prod(shape))
    if not reuse or size > WORKSPACE_LIMIT:
        return np.empty(shape), np.empty(shape)
    held = getattr(_workspace, slot, None)
    if held is None or held.shape[1] < size:  # grown by half at least: few regrowths
        grown = 0 if held is None else held.shape[1] + held.shape[1] // 2
        held = np.empty((2, min(max(size, grown), WORKSPACE_LIMIT)))
        setattr(_workspace, slot, held)
    return held[0, :size].reshape(shape), held[1, :size].reshape(shape)


def sparse_table(table: np.ndarray):
    """The nonzero entries of ``table`` (M, C) column by column, rows in increasing
    order: (starts (C + 1,), rows, values), a compressed-column form."""
    table = np.asarray(table, dtype=np.float64)
    mask = table.T != 0
    starts = np.concatenate([[0], np.cumsum(mask.sum(axis=1))]).astype(np.int64)
    rows = np.nonzero(mask)[1].astype(np.int64)
    values = np.ascontiguousarray(table.T[mask])
    return starts, rows, values


@njit(cache=True, nogil=True)
def polynomial_table(values, gradients, coef, free_rows, free_cols, sensitivities):
    """:func:`sparse_table` of :meth:`.shooting.Integrator._polynomial_table` (with
    ``sensitivities``) or of the field's table ``values @ coef.T`` alone, made in one
    call. Each feature is one monomial, and each monomial's gradient by a state one
    integer times another, so every entry of the tables is one product (the rest of a
    matrix product's sum is zeros): the entries are those of numpy's products to the
    bit."""
    n_mono, n_feat = values.shape
    n, n_free = coef.shape[0], free_rows.shape[0]
    width = n + n * n + n * (n + n_free) if sensitivities else n
    table = np.zeros((n_mono, width))
    for m in range(n_mono):
        for i in range(n):
            acc = 0.0
            for f in range(n_feat):
                acc += values[m, f] * coef[i, f]
            table[m, i] = acc
            if sensitivities:
                for s in range(n):
                    acc = 0.0
                    for f in range(n_feat):
                        acc += gradients[m, f * n + s] * coef[i, f]
                    table[m, n + i * n + s] = acc
        if sensitivities:
            for q in range(n_free):
                table[m, n + n * n + free_rows[q] * (n + n_free) + n + q] = \
                    values[m, free_cols[q]]
    starts = np.zeros(width + 1, dtype=np.int64)
    for c in range(width):
        count = 0
        for m in range(n_mono):
            if table[m, c] != 0:
                count += 1
        starts[c + 1] = starts[c] + count
    rows = np.empty(starts[width], dtype=np.int64)
    entries = np.empty(starts[width])
    p = 0
    for c in range(width):
        for m in range(n_mono):
            if table[m, c] != 0:
                rows[p], entries[p] = m, table[m, c]
                p += 1
    return starts, rows, entries


@njit(cache=True, nogil=True)
def _field(y, basis, degree, starts, rows, values, n_value, bound, mono, powers, out, slope):
    """The slope ``slope`` (n, W, K) at ``y`` (n, W, K): states ``y[:, 0]``, and for
    W > 1 their sensitivities ``y[:, 1:]``; the segments last, so that every loop runs
    over them. Returns False where a state is out of bounds (nothing else is then
    written)."""
    n, w, k_rows = y.shape
    for s in range(n):
        for k in range(k_rows):
            v = y[s, 0, k]
            if not (v <= bound and -v <= bound):  # NaN fails both
                return False
    for s in range(n):
        for k in range(k_rows):
            powers[s, 0, k] = 1.0
        for d in range(degree):
            for k in range(k_rows):
                powers[s, d + 1, k] = powers[s, d, k] * y[s, 0, k]
    for m in range(basis.shape[0]):
        for k in range(k_rows):
            mono[m, k] = powers[0, basis[m, 0], k]
        for s in range(1, n):
            e = basis[m, s]
            for k in range(k_rows):
                mono[m, k] = mono[m, k] * powers[s, e, k]
    for c in range(starts.shape[0] - 1):
        for k in range(k_rows):
            out[c, k] = 0.0
        for p in range(starts[c], starts[c + 1]):
            r, v = rows[p], values[p]
            for k in range(k_rows):
                out[c, k] += mono[r, k] * v
    for i in range(n):
        for k in range(k_rows):
            slope[i, 0, k] = out[i, k]
    # the sensitivities' slopes: the Jacobian times the sensitivities, plus the
    # field's derivatives by the parameters; summed column by column as a dot product
    # would be (from zero, then the parameter's term), the segments innermost
    jac, extra = n_value, n_value + n * n
    for i in range(n):
        for j in range(w - 1):
            target = slope[i, 1 + j]
            for k in range(k_rows):
                target[k] = 0.0
            for col in range(n):
                row, sens = out[jac + i * n + col], y[col, 1 + j]
                for k in range(k_rows):
                    target[k] += row[k] * sens[k]
            row = out[extra + i * (w - 1) + j]
            for k in range(k_rows):
                target[k] += row[k]
    return True


@njit(cache=True, nogil=True)
def integrate(z0, steps, basis, degree, starts, rows, values, n_value, bound, z, dz):
    """Classical Runge-Kutta (the 3/8 rule) of ``z0`` (n, W, K) over ``steps`` (S, K):
    the states and their slopes at every grid point written into ``z`` and ``dz``
    ((S + 1, n, W, K) each), and whether every stage stayed within ``bound``."""
    n, w, k_rows = z0.shape
    n_steps = steps.shape[0]
    z[0] = z0
    t = np.empty_like(z0)
    k2 = np.empty_like(z0)
    k3 = np.empty_like(z0)
    k4 = np.empty_like(z0)
    mono = np.empty((basis.shape[0], k_rows))
    powers = np.empty((n, degree + 1, k_rows))
    out = np.empty((starts.shape[0] - 1, k_rows))
    for i in range(n_steps):
        y, k1, dt = z[i], dz[i], steps[i]
        if not _field(y, basis, degree, starts, rows, values, n_value, bound, mono,
                      powers, out, k1):
            return False
        for s in range(n):
            for j in range(w):
                for k in range(k_rows):
                    t[s, j, k] = k1[s, j, k] * dt[k] * _ONE_THIRD + y[s, j, k]
        if not _field(t, basis, degree, starts, rows, values, n_value, bound, mono,
                      powers, out, k2):
            return False
        for s in range(n):
            for j in range(w):
                for k in range(k_rows):
                    t[s, j, k] = (k2[s, j, k] - k1[s, j, k] * _ONE_THIRD) * dt[k] + y[s, j, k]
        if not _field(t, basis, degree, starts, rows, values, n_value, bound, mono,
                      powers, out, k3):
            return False
        for s in range(n):
            for j in range(w):
                for k in range(k_rows):
                    t[s, j, k] = (k1[s, j, k] - k2[s, j, k] + k3[s, j, k]) * dt[k] + y[s, j, k]
        if not _field(t, basis, degree, starts, rows, values, n_value, bound, mono,
                      powers, out, k4):
            return False
        after = z[i + 1]
        for s in range(n):
            for j in range(w):
                for k in range(k_rows):
                    b = (k2[s, j, k] + k3[s, j, k]) * 3.0 + k1[s, j, k] + k4[s, j, k]
                    after[s, j, k] = b * dt[k] * 0.125 + y[s, j, k]
    if not _field(z[n_steps], basis, degree, starts, rows, values, n_value, bound, mono,
                  powers, out, dz[n_steps]):
        return False
    return True


def hermite(z, dz, rows, w00, w10, w01, w11, components):
    """Cubic Hermite interpolation of the grid values ``z`` and slopes ``dz`` (G, n,
    W, K) (:func:`integrate`'s) of the first ``components`` states: (P, components, W)
    at the P samples whose left grid point is ``rows`` (segment times G plus grid
    index), weights as :func:`.shooting._hermite_table` makes them, summed in
    :func:`.shooting._hermite`'s order. The grid values are first copied segment by
    segment ((K, G, components, W), into this thread's second workspace), so that each
    sample reads two contiguous blocks: read in place, every value is a stride of K
    apart (2.7 times the time)."""
    g, _, w, n_seg = z.shape
    zk, dzk = _outputs((n_seg, g, components, w), True, "hermite")
    return _hermite(z, dz, rows, w00, w10, w01, w11, components, zk, dzk)


@njit(cache=True, nogil=True)
def _hermite(z, dz, rows, w00, w10, w01, w11, components, zk, dzk):
    g, _, w, n_seg = z.shape
    for j in range(g):
        for s in range(components):
            for i in range(w):
                for k in range(n_seg):
                    zk[k, j, s, i] = z[j, s, i, k]
                    dzk[k, j, s, i] = dz[j, s, i, k]
    out = np.empty((rows.shape[0], components, w))
    for p in range(rows.shape[0]):
        k = rows[p] // g
        j = rows[p] - k * g
        a, b, c, d = w00[p], w10[p], w01[p], w11[p]
        z0, d0, z1, d1 = zk[k, j], dzk[k, j], zk[k, j + 1], dzk[k, j + 1]
        for s in range(components):
            for i in range(w):
                out[p, s, i] = z0[s, i] * a + d0[s, i] * b + z1[s, i] * c + d1[s, i] * d
    return out
