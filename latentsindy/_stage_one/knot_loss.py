"""The training loss on the decoder's knots: the numpy step's misfit, roughness and
magnitude.

timeVAE draws each coefficient as a piecewise-linear function through ``n_knots``
equally spaced knots, read at the sample times. On a uniform grid with at least two
samples per knot interval every term of the loss is a fixed function of the knots:

* the weighted squared misfit ``sum_t w_t (theta_t . xi_t - xdot_t)^2`` is a quadratic
  form in the knots whose matrix is block-tridiagonal (each sample reads two adjacent
  knots), built once in float64; its value and gradient cost a few products of the
  knots' size instead of the samples'. With a wide library (``K F > 2 T``) the form
  costs more than the samples, and the misfit is read at the samples instead;
* the roughness's differences of consecutive samples are fixed combinations of the
  knots' differences: a sample step inside a knot interval is a fixed share of that
  interval's difference (all steps of an interval share its sign), one across a knot is
  a mix of two; a second difference is zero in exact arithmetic unless its three
  samples straddle a knot, and only those are evaluated (on the samples in float32 the
  others are rounding noise; their gradient, a second difference itself, cancels in the
  knots' gradient up to rounding, so leaving them out changes the rounding only);
* the mean magnitude ``mean_t |xi_t|`` is summed per knot interval: where both knots
  have one sign, from the sum of its samples' interpolation weights; where the sign
  changes, sample by sample (a padded table of their weights).

The values are those of :mod:`.loss` (the same definitions and shares, not an
approximation): tests hold each term and its gradient to the samples' formulas and to
:func:`.loss.loss_terms` in float64, and the numpy step's gradients to autograd's. The
arithmetic runs in the data's precision (float32 in training).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sparse

from ..generators._knots import curve_rows, interpolation, knot_grid, step_pairs
from . import step_kernels as kernels
from .loss import BEND_SHARE, TV_SHARE

_CHUNK = 8192  # samples per block when the misfit's matrix is built


class KnotLoss:
    """The misfit, roughness and magnitude terms of the loss from the knots' values.

    Parameters
    ----------
    theta : (B, T, F) array, xdot, weights : (B, T, n) arrays
        In one precision (float32 in training), the knots' too.
    n_knots : int
    """

    def __init__(self, theta, xdot, weights, n_knots):
        n_traj, n_times, n_features = theta.shape
        self.dtype = theta.dtype
        n_states = xdot.shape[-1]
        left, frac = knot_grid(n_times, n_knots)
        self.n_times = n_times
        self.count = n_traj * n_times * n_states  # the misfit is a mean over these
        # the quadratic form costs about K F^2 per equation, the samples' misfit T F:
        # with a wide library (K F > 2 T: measured at 2000 samples, 21 terms took 2.4 ms a
        # step against 0.43) the misfit reads the series at the samples instead
        self.on_samples = n_knots * n_features > 2 * n_times
        if self.on_samples:
            self.theta, self.xdot, self.weights = theta, xdot, weights
            self.to_samples, self.to_knots = interpolation(left, frac, n_knots)
        else:
            self._misfit_matrix(theta, xdot, weights, left, frac, n_knots)
        self._differences(left, frac, n_knots)
        # the samples of each interval (``counts``), padded: their weights on the
        # interval's right knot
        counts = np.bincount(left, minlength=n_knots - 1)
        width = int(counts.max())
        self.share = np.zeros((n_knots - 1, width), self.dtype)
        self.counts = counts
        slot = np.arange(n_times) - np.concatenate([[0], np.cumsum(counts)])[left]
        self.share[left, slot] = frac
        self.share_sums = np.bincount(left, weights=frac, minlength=n_knots - 1)

    def _misfit_matrix(self, theta, xdot, weights, left, frac, n_knots):
        """The misfit as ``x' G x - 2 c' x + base`` in the knots' values ``x`` (K, n, F)
        flattened: ``G`` sparse (block-tridiagonal), ``c`` and ``base``, in float64."""
        n_features, n_states = theta.shape[-1], xdot.shape[-1]
        n_ff = n_features * n_features
        diag = np.zeros((n_knots, n_states, n_ff))
        upper = np.zeros((n_knots, n_states, n_ff))
        cross = np.zeros((n_knots, n_states, n_features))
        base = 0.0
        for b in range(theta.shape[0]):
            for lo in range(0, theta.shape[1], _CHUNK):
                hi = min(lo + _CHUNK, theta.shape[1])
                th = theta[b, lo:hi].astype(np.float64)
                w = weights[b, lo:hi].astype(np.float64)
                y = xdot[b, lo:hi].astype(np.float64)
                at, f = left[lo:hi], frac[lo:hi]
                outer = (th[:, :, None] * th[:, None, :]).reshape(len(th), -1)
                for i in range(n_states):
                    wo = outer * w[:, i, None]
                    _add_rows(diag[:, i], at, wo * ((1 - f) ** 2)[:, None])
                    _add_rows(diag[:, i], at + 1, wo * (f**2)[:, None])
                    _add_rows(upper[:, i], at, wo * ((1 - f) * f)[:, None])
                    wy = th * (w[:, i] * y[:, i])[:, None]
                    _add_rows(cross[:, i], at, wy * (1 - f)[:, None])
                    _add_rows(cross[:, i], at + 1, wy * f[:, None])
                base += float(np.sum(w * y * y))
        # entry (k, i, f) x (k', i, g) of G, for k' = k (diag) and k' = k + 1 (upper)
        k, i, f, g = np.meshgrid(np.arange(n_knots), np.arange(n_states),
                                 np.arange(n_features), np.arange(n_features), indexing="ij")
        row = (k * n_states + i) * n_features + f
        col = (k * n_states + i) * n_features + g
        step = n_states * n_features  # the next knot's block
        upper_rows, upper_cols = row[:-1].ravel(), col[:-1].ravel() + step
        values = np.concatenate([diag.ravel(), upper[:-1].ravel(), upper[:-1].ravel()])
        rows = np.concatenate([row.ravel(), upper_rows, upper_cols])
        cols = np.concatenate([col.ravel(), upper_cols, upper_rows])
        size = n_knots * step
        self.gram = sparse.csr_matrix((values, (rows, cols)), shape=(size, size))
        self.cross, self.base = cross.ravel(), base

    def _differences(self, left, frac, n_knots):
        """The samples' steps and second differences as combinations of the knots'
        differences ``d_k`` (``generators._knots``): the steps inside interval k add
        up to ``inside[k] |d_k|`` (one sign); the step across knot k (one at most) is
        ``u d_{k-1} + v d_k``; each second difference that can bend mixes the same
        two, ``a d_{k-1} + b d_k``, laid out as (rows per knot, K - 2)."""
        c1, w1, c2, w2 = step_pairs(left, frac)
        across = w2 != 0
        self.inside64 = np.bincount(c1[~across], weights=w1[~across], minlength=n_knots - 1)
        self.inside = self.inside64.astype(self.dtype)
        self.u = np.zeros(n_knots - 2, self.dtype)  # at knots 1 .. K - 2
        self.v = np.zeros(n_knots - 2, self.dtype)
        self.u[c2[across] - 1], self.v[c2[across] - 1] = w1[across], w2[across]
        _, k, a, b = curve_rows(left, frac, n_knots)
        per_knot = np.bincount(k - 1, minlength=n_knots - 2)
        slot = np.arange(len(k)) - np.concatenate([[0], np.cumsum(per_knot)])[k - 1]
        self.a = np.zeros((max(int(per_knot.max(initial=0)), 1), n_knots - 2), self.dtype)
        self.b = np.zeros_like(self.a)
        self.a[slot, k - 1], self.b[slot, k - 1] = a, b

    def misfit(self, xi):
        """Mean weighted squared misfit and its gradient by ``xi`` (K, n, F)."""
        if self.on_samples:
            return self._misfit_on_samples(xi)
        x = xi.astype(np.float64).ravel()
        g = np.empty_like(x)  # G x - c
        gram = self.gram
        total = kernels.quadratic_form(gram.indptr, gram.indices, gram.data, self.cross, x,
                                       g) + self.base  # x'Gx - 2c'x + base
        grad = ((2.0 / self.count) * g).astype(self.dtype).reshape(xi.shape)
        return max(total, 0.0) / self.count, grad  # (an exact fit can round below 0)

    def _misfit_on_samples(self, xi):
        """The misfit read at the samples (a wide library), its gradient summed back
        onto the knots interval by interval."""
        xi_t = np.asarray(self.to_samples @ xi.reshape(xi.shape[0], -1)).reshape(
            -1, *xi.shape[1:])  # (T, n, F)
        resid = np.einsum("btf,tnf->btn", self.theta, xi_t) - self.xdot
        wr = self.weights * resid
        mse = float(np.mean(wr * resid))
        g = np.einsum("btn,btf->tnf", wr * self.dtype.type(2.0 / resid.size), self.theta)
        grad = np.asarray(self.to_knots @ g.reshape(g.shape[0], -1))
        return mse, grad.reshape(xi.shape)

    def roughness(self, xi):
        """:func:`.loss.roughness` of the samples per term (n, F), from the knots'
        values ``xi`` (K, n, F), and its gradient by them."""
        flat = np.ascontiguousarray(xi.reshape(xi.shape[0], -1))  # (K, nF)
        value = np.empty(flat.shape[1], self.dtype)
        grad = np.empty_like(flat)
        kernels.knot_roughness(flat, self.inside, self.inside64, self.u, self.v, self.a,
                               self.b, TV_SHARE / (self.n_times - 1),
                               BEND_SHARE / (self.n_times - 2), value, grad,
                               np.empty((flat.shape[0] - 1, flat.shape[1]), self.dtype))
        return value.reshape(xi.shape[1:]), grad.reshape(xi.shape)

    def magnitude(self, xi):
        """``mean_t |xi_t|`` per term (n, F), and the gradient of ``sum_t |xi_t|`` by
        the knots (K, n, F)."""
        flat = np.ascontiguousarray(xi.reshape(xi.shape[0], -1))  # (K, nF)
        size = np.empty(flat.shape[1], self.dtype)
        grad = np.empty_like(flat)
        kernels.knot_magnitude(flat, self.share, self.counts, self.share_sums,
                               self.n_times, size, grad)
        return size.reshape(xi.shape[1:]), grad.reshape(xi.shape)


def _add_rows(target, rows, values):
    """``target[rows] += values`` with repeated rows summed, ``rows`` sorted."""
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    target[rows[starts]] += np.add.reduceat(values, starts, axis=0)
