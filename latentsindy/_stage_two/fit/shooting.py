"""Multiple shooting: a closed system integrated segment by segment against the data.

Each trajectory is cut into segments of equal duration; every segment starts from a
free state (observed and hidden) and is integrated by classical Runge-Kutta on a
fixed grid (:func:`rk4`, so the cost is known in advance) together with its forward
sensitivities with respect to the start and to the free coefficients. States at the
sample times come from cubic Hermite interpolation between grid points (the same
order as the integrator). The observed samples give the data residuals; the gap
between a segment's end and the next segment's start gives the continuity residuals.

The least-squares normal equations this gives have an arrow structure (coefficients
couple everything, each start couples only its own segment and its neighbours); they
are assembled and solved in :mod:`.normal_equations`.

Every trajectory is a :class:`Group` of segments on one grid; the groups of a panel
(one per recording) are integrated side by side (:mod:`.batches`), each segment on its
own group's grid: the arithmetic of integrating group by group, in few calls.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from .field import FeatureMap, ParametricSystem


class BlowUp(Exception):
    """A segment left the bounded region (or became non-finite)."""


@dataclass
class Group:
    """Segments of one trajectory: equal duration, one integration grid."""

    trajectory: int
    first: int  # index of the first segment in the global list
    n_segments: int
    grid: torch.Tensor  # (G,) relative times of the integration grid (on the device)
    positions: torch.Tensor  # (K, M) relative sample times, padded (on the device)
    observed: torch.Tensor  # (K, M, n_observed) data (padded)
    mask: torch.Tensor  # (K, M) bool: a real sample
    sample_index: np.ndarray  # (K, M) index of the sample in its trajectory (-1: padding)
    starts: np.ndarray  # (K,) absolute start times
    # the Hermite interpolation's rows and weights, made at the first integration
    hermite: dict = field(default_factory=dict, repr=False, compare=False)
    steps: dict = field(default_factory=dict, repr=False, compare=False)  # the grid's steps


def make_groups(times, observed, duration, step, device="cpu"):
    """Cut every trajectory into segments of about ``duration`` with grid ``step``; the
    integration grid and sample positions live on ``device``, the data on the CPU."""
    groups, first = [], 0
    for k, (t, x) in enumerate(zip(times, observed, strict=True)):
        span = float(t[-1] - t[0])
        n_seg = max(1, int(round(span / duration)))
        seg = span / n_seg
        n_steps = max(1, int(np.ceil(seg / step)))
        which = np.minimum(((t - t[0]) / seg).astype(int), n_seg - 1)
        counts = np.bincount(which, minlength=n_seg)
        m = int(counts.max())
        pos = np.zeros((n_seg, m))
        obs = np.zeros((n_seg, m, x.shape[1]))
        mask = np.zeros((n_seg, m), dtype=bool)
        index = np.full((n_seg, m), -1)
        for s in range(n_seg):
            rows = np.flatnonzero(which == s)
            pos[s, :len(rows)] = t[rows] - (t[0] + s * seg)
            obs[s, :len(rows)] = x[rows]
            mask[s, :len(rows)] = True
            index[s, :len(rows)] = rows
        as_t = lambda a, on="cpu": torch.as_tensor(a, dtype=torch.float64, device=on)  # noqa: E731
        groups.append(Group(k, first, n_seg, as_t(np.linspace(0.0, seg, n_steps + 1), device),
                            as_t(np.clip(pos, 0.0, seg), device), as_t(obs),
                            torch.as_tensor(mask),
                            index, t[0] + seg * np.arange(n_seg)))
        first += n_seg
    return groups


@dataclass
class Batch:
    """Groups integrated side by side in one call. Each segment keeps its own group's
    grid; shorter grids are padded with steps of length zero, over which Runge-Kutta
    leaves a state as it is, so every segment's arithmetic is its group's alone."""

    members: list  # (index in the groups, first row here, segments, sample positions)
    grid: torch.Tensor  # (K, G) relative grid times of every segment (on the device)
    positions: torch.Tensor  # (K, M) relative sample times, padded (on the device)
    lengths: np.ndarray  # (K,) grid points of each segment before the padding
    hermite: dict = field(default_factory=dict, repr=False, compare=False)
    steps: dict = field(default_factory=dict, repr=False, compare=False)  # rk4's, per device


class Integrator:
    """Integrates batches of segments of one system with forward sensitivities.

    Polynomial fields on the CPU are integrated by one compiled loop
    (:mod:`.compiled`), anything else in torch on ``device``. The arithmetic is the same
    up to the order of a sum; what differs is the cost of an operation: the refinement
    integrates thousands of small batches (a few segments, a few states), where each
    array operation's overhead costs more than its arithmetic (in numpy, the same steps
    took 2.6 times as long on the Hindmarsh-Rose neuron; in torch, 3.5 times numpy's on
    Lorenz from x, the states and sensitivities equal to 3e-15).
    """

    def __init__(self, system: ParametricSystem, bound: float, features=None, device="cpu"):
        self.system = system
        self.features = features or FeatureMap(system.features, system.symbols)
        self.device = torch.device(device)
        self.rows, self.cols = np.nonzero(system.free)
        self.bound = bound
        self.in_numpy = self.device.type == "cpu" and self.features.exponents is not None

    def _check(self, y):
        if torch.is_tensor(y):  # one reduction, one wait for the device
            top = float(y.abs().max())
        else:  # max |y| as the larger of max y and -min y: no temporary array (numpy's
            # max and min both return NaN when any entry is NaN, so the test below sees
            # it: Python's max of the two alone would not)
            top = max(float(y.max()), -float(y.min()))
        if not top <= self.bound:  # NaN fails the comparison too
            raise BlowUp()

    def _field(self, coef):
        if self.features.exponents is not None:
            return self._polynomial_field(coef)
        n = len(self.system.state_names)
        rows = torch.as_tensor(self.rows, device=self.device)
        cols = n + torch.arange(len(self.rows), device=self.device)
        take = torch.as_tensor(self.cols, device=self.device)

        def func(z):
            y = z[..., 0]
            self._check(y)
            phi, dphi = self.features(y)
            sens = (coef @ dphi) @ z[..., 1:]  # d/dt S = J S (+ df/dcoef below)
            sens[..., rows, cols] += phi[..., take]
            return torch.cat([(phi @ coef.T)[..., None], sens], dim=-1)

        return func

    def _polynomial_field(self, coef):
        """The field, its Jacobian and its derivatives by the free coefficients from one
        product of the monomials with a table made for ``coef``: the sensitivity
        equations' right-hand side ``(f, J S + df/dcoef)`` in a handful of array
        operations. The same arithmetic as the feature map's path: the tables hold only
        0/1 and exponents. ``coef`` is a numpy array or a tensor, and so is the field."""
        table = self._polynomial_table(coef)
        fm, n = self.features, len(self.system.state_names)
        first, second = n, n + n * n

        def func(z):
            y = z[..., 0]
            self._check(y)
            lead = y.shape[:-1]
            out = fm.monomials(y) @ table
            sens = out[..., first:second].reshape(*lead, n, n) @ z[..., 1:]
            sens += out[..., second:].reshape(*lead, n, n + len(self.rows))
            return _cat([out[..., :first, None], sens], -1)

        return func

    def _polynomial_table(self, coef):
        """The table (M, n + n n + n (n + free)) whose product with the monomials gives
        the field, its Jacobian and its derivatives by the start and the free
        coefficients (a numpy array or a tensor, like ``coef``)."""
        fm, n = self.features, len(self.system.state_names)
        xp = np if isinstance(coef, np.ndarray) else torch
        values, grads = fm.tables(coef)  # (M, F), (M, F * n)
        n_monomials, n_free = values.shape[0], len(self.rows)
        extra = xp.zeros((n_monomials, n, n + n_free), dtype=coef.dtype)
        if xp is torch:
            extra = extra.to(coef.device)
        extra[:, self.rows, n + np.arange(n_free)] = values[:, self.cols]
        jac = xp.einsum("mfs,if->mis", grads.reshape(n_monomials, fm.n_features, n), coef)
        return _cat([values @ coef.T, jac.reshape(n_monomials, -1),
                     extra.reshape(n_monomials, -1)], -1)

    def _plain(self, coef):
        if self.features.exponents is not None:
            table = self.features.tables(coef)[0] @ coef.T

            def polynomial(y):
                self._check(y)
                return self.features.monomials(y) @ table

            return polynomial

        def func(y):
            self._check(y)
            return self.features(y, gradients=False)[0] @ coef.T

        return func

    def run(self, coef, starts, group: Group | Batch, sensitivities=True,
            components=None, as_numpy=False):
        """States (and sensitivities) at the group's sample times and at segment ends,
        as tensors on the CPU (numpy arrays with ``as_numpy``).

        Returns ``(values, ends)``; with sensitivities each is a pair (state, S) where
        S is d state / d(start, free coefficients), shape (..., n, n + n_free). With
        ``components``, only the first ``components`` states (the observed ones, say)
        are interpolated to the sample times; the ends hold every state.
        """
        if self.in_numpy:  # compiled.py: the same steps and interpolation, one call each
            from . import compiled  # numba: imported at the first integration, not with the package

            if "numpy" not in group.hermite:
                group.hermite["numpy"] = _hermite_table(group, "numpy")
            out = compiled.run(self, np.asarray(coef, dtype=np.float64),
                               np.asarray(starts, dtype=np.float64), group, sensitivities,
                               components, group.hermite["numpy"], group.steps)
            if out is None:  # a state left the bound
                raise BlowUp()
            values, ends = out if as_numpy else (torch.from_numpy(a) for a in out)
        else:
            values, ends = self._run_torch(coef, starts, group, sensitivities, components)
            if as_numpy:
                values, ends = values.numpy(), ends.numpy()
        if sensitivities:
            return (values[..., 0], values[..., 1:]), (ends[..., 0], ends[..., 1:])
        return values, ends

    @torch.no_grad()
    def _run_torch(self, coef, starts, group, sensitivities, components):
        """:meth:`run`'s values and ends, sensitivities along the last axis, in torch
        (without autograd: a context entered here only, as it costs microseconds a call
        and the compiled path has no use for it)."""
        like = dict(dtype=torch.float64, device=self.device)
        coef = torch.as_tensor(coef, **like)
        y0 = torch.as_tensor(starts, **like)
        grid = group.grid
        n, k = y0.shape[-1], y0.shape[0]
        if sensitivities:
            eye = torch.eye(n, **like).expand(k, n, n)
            rest = torch.zeros(k, n, len(self.rows), **like)
            z0 = _cat([y0[..., None], eye, rest], -1)
            func = self._field(coef)
        else:
            z0, func = y0, self._plain(coef)
        z, dz = rk4(func, z0, grid, getattr(group, "steps", None))  # (G, K, ...)
        z, dz = z.swapaxes(0, 1), dz.swapaxes(0, 1)  # (K, G, ...)
        ends = z[:, -1]
        if components is not None:  # the same arithmetic on fewer states
            z, dz = z[:, :, :components], dz[:, :, :components]
        # the caller's algebra (normal equations, residuals) is on the CPU
        return _hermite(z, dz, group).cpu(), ends.cpu()


def _cat(arrays, axis):
    if isinstance(arrays[0], np.ndarray):
        return np.concatenate(arrays, axis)
    return torch.cat(arrays, axis)


def rk4(func, y0, grid, cache=None):
    """Classical Runge-Kutta (the 3/8 rule, torchdiffeq's fixed-grid ``rk4``, the same
    arithmetic) on ``grid``: the states at every grid time and their slopes ``func``
    there, two arrays (G, ...), numpy arrays or tensors like ``y0``. Written out because
    the refinement integrates thousands of small batches, where the general solver's
    bookkeeping cost as much as the arithmetic. A grid (K, G) gives each of the K rows
    of ``y0`` its own steps (a :class:`Batch`; kept in the dict ``cache``, if given,
    once made). A step's first stage is the slope at its start, so only the last grid
    point's slope costs another evaluation."""
    if grid.ndim == 1:
        steps = np.diff(np.asarray(grid.tolist())).tolist()
    else:
        key = ("numpy" if isinstance(y0, np.ndarray) else y0.device, y0.ndim)
        steps = None if cache is None else cache.get(key)
        if steps is None:
            shape = (-1, *([1] * (y0.ndim - 1)))
            steps = [a.reshape(shape) for a in np.diff(np.asarray(grid.tolist()), axis=1).T]
            if not isinstance(y0, np.ndarray):
                steps = [torch.as_tensor(a, dtype=y0.dtype, device=y0.device) for a in steps]
            if cache is not None:
                cache[key] = steps
    if isinstance(y0, np.ndarray):
        return _rk4_numpy(func, y0, steps)
    out, slopes = [y0], []
    y = y0
    for dt in steps:
        k1 = func(y)
        k2 = func(y + dt * k1 * _ONE_THIRD)
        k3 = func(y + dt * (k2 - k1 * _ONE_THIRD))
        k4 = func(y + dt * (k1 - k2 + k3))
        y = y + (k1 + 3 * (k2 + k3) + k4) * dt * 0.125
        out.append(y)
        slopes.append(k1)
    slopes.append(func(y))
    return torch.stack(out), torch.stack(slopes)


def _rk4_numpy(func, y0, steps):
    """:func:`rk4` in numpy, each step's stages and state written in place into
    preallocated arrays: the same operations in the same order (products and sums
    with their operands swapped, which IEEE arithmetic leaves exact), fewer arrays."""
    z = np.empty((len(steps) + 1, *y0.shape), dtype=y0.dtype)
    dz = np.empty_like(z)
    z[0] = y0
    t = np.empty_like(y0)
    for i, dt in enumerate(steps):
        y, after = z[i], z[i + 1]
        k1 = dz[i] = func(y)
        np.multiply(k1, dt, out=t)  # y + dt * k1 / 3
        t *= _ONE_THIRD
        t += y
        k2 = func(t)
        np.multiply(k1, _ONE_THIRD, out=t)  # y + dt * (k2 - k1 / 3)
        np.subtract(k2, t, out=t)
        t *= dt
        t += y
        k3 = func(t)
        np.subtract(k1, k2, out=t)  # y + dt * (k1 - k2 + k3)
        t += k3
        t *= dt
        t += y
        k4 = func(t)
        np.add(k2, k3, out=after)  # y + (k1 + 3 (k2 + k3) + k4) dt / 8
        after *= 3
        after += k1
        after += k4
        after *= dt
        after *= 0.125
        after += y
    dz[-1] = func(z[-1])
    return z, dz


_ONE_THIRD = 1 / 3


def _hermite(z, dz, group: Group | Batch):
    """Cubic Hermite interpolation of grid values z (K, G, ...) (numpy arrays or
    tensors) at the group's sample positions: (K, M, ...)."""
    key = "numpy" if isinstance(z, np.ndarray) else z.device
    if key not in group.hermite:
        group.hermite[key] = _hermite_table(group, key)
    rows, next_rows, w00, w10, w01, w11 = group.hermite[key]
    k, g = z.shape[:2]
    rest = z.shape[2:]
    z, dz = z.reshape(k * g, *rest), dz.reshape(k * g, *rest)
    shape = (-1, *([1] * len(rest)))
    w00, w10, w01, w11 = (w.reshape(shape) for w in (w00, w10, w01, w11))
    # in place (indexing by rows copies): w00 z + w10 dz + w01 z' + w11 dz', summed left
    # to right, with fewer arrays; z and dz are float64, as Integrator.run makes them
    values = z[rows]
    values *= w00
    for weight, source, at in ((w10, dz, rows), (w01, z, next_rows), (w11, dz, next_rows)):
        term = source[at]
        term *= weight
        values += term
    return values.reshape(k, group.positions.shape[1], *rest)


def _hermite_table(group: Group | Batch, on):
    """Rows of the flattened grid values (segment, grid index) left of each sample, those
    rows plus one (right of it), and the Hermite weights of the values and slopes at
    both ends (the slopes' times the step), for the group's positions: made once per
    group (and device)."""
    grid = group.grid.cpu().numpy()
    positions = group.positions.cpu().numpy()
    if grid.ndim == 1:
        h = grid[1] - grid[0]
        j = np.clip(np.floor(positions / h).astype(np.int64), 0, len(grid) - 2)
        s = (positions - grid[j]) / h
    else:  # a batch: each segment's own step, within its own (unpadded) grid
        h = (grid[:, 1] - grid[:, 0])[:, None]
        j = np.clip(np.floor(positions / h).astype(np.int64), 0, group.lengths[:, None] - 2)
        s = (positions - np.take_along_axis(grid, j, axis=1)) / h
    s2, s3 = s * s, s * s * s
    rows = (np.arange(len(positions))[:, None] * grid.shape[-1] + j).ravel()
    weights = [(2 * s3 - 3 * s2 + 1), (s3 - 2 * s2 + s) * h, (-2 * s3 + 3 * s2), (s3 - s2) * h]
    table = [rows, rows + 1] + [w.ravel() for w in weights]
    if on == "numpy":
        return table
    return [torch.as_tensor(a, device=on) for a in table]


STEP = 0.2  # integrator step times the fastest local rate (see stable_step)


def stable_step(integrator, guesses, coef):
    """A Runge-Kutta step resolving the fastest local rate of the initial system
    (spectral radius of the Jacobian along the guessed states, 99th percentile): ``STEP``
    radians of the fastest oscillation per step. At 0.3 RK4's numerical damping of an
    oscillator (about (h w)^6 / 144 per step) was large enough on exact data to be
    compensated by a spurious term; at 0.2 it is ten times smaller."""
    y = torch.as_tensor(np.vstack(guesses)[::max(1, len(np.vstack(guesses)) // 2000)])
    _, dphi = integrator.features(y)
    jac = torch.einsum("bfs,if->bis", dphi, torch.as_tensor(coef, dtype=torch.float64))
    rate = torch.linalg.eigvals(jac).abs().max(dim=-1).values.numpy()
    fastest = float(np.quantile(rate, 0.99)) if len(rate) else 0.0
    return STEP / fastest if fastest > 0 else np.inf
