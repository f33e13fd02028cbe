"""The normal equations of multiple shooting (J^T J and J^T r over the free
coefficients and the segments' starts) and their solution.

They have an arrow structure: the free coefficients couple everything, each start
couples only its own segment and, through continuity, its neighbours'. Up to ``DENSE``
unknowns (a two-state system of a few dozen segments) they are held and solved
densely, which costs least there; beyond it they are held by their blocks
(:class:`ArrowMatrix`: the coefficients' block, the coupling of starts to
coefficients, and the starts' block tridiagonal in segments) and solved through the
starts' banded Cholesky factor and the coefficients' Schur complement: memory and time
grow with the number of segments, not with its square or cube (a three-state system
of 100 segments, 320 unknowns: assembly and two damped solves 0.4 and 0.4 ms by
blocks, 0.6 and 2.0 ms densely; at 86 unknowns the two cost the same, at 130 the
blocks save a quarter).
"""

from __future__ import annotations

import warnings
from functools import lru_cache

import numpy as np
import scipy.sparse as sps
from numba import njit
from scipy.sparse.linalg import MatrixRankWarning, spsolve

from ..._core.banded import cholesky_upper, solve_upper

# normal equations with up to this many unknowns are assembled and solved densely
# (LAPACK), larger ones by their blocks (ArrowMatrix): the two cost the same between
# 86 and 130 unknowns (benchmarks/README.md, speed.py --normal-equations)
DENSE = 100


class NormalEquations:
    """Block assembly of J^T J and J^T r for (free coefficients, segment starts): a dense
    array when the system has at most ``DENSE`` unknowns, else an :class:`ArrowMatrix`.

    Every block of rows touches the free coefficients and the starts of one segment or
    of two consecutive ones (a continuity gap)."""

    def __init__(self, n_free, n_segments, n_states):
        self.p, self.k, self.n = n_free, n_segments, n_states
        self.size = n_free + n_segments * n_states
        self.dense = self.size <= DENSE
        # dense: per added block the unknowns its gradient entries go to and those
        # entries, and the flat (row * size + col) indices of its Gram entries and those
        # entries (summed in the order added); else the arrow's blocks, summed as added
        self.grad_index, self.grads, self.where, self.vals = [], [], [], []
        self.arrow = None if self.dense else ArrowMatrix.zeros(n_free, n_segments, n_states)
        self.cost, self._grad = 0.0, None

    def add(self, jac, resid, segments):
        """Rows ``jac`` (B, R, P + n * len(segments)) for the residuals ``resid`` (B, R)
        of the blocks whose starts are ``segments`` (B, 1) or consecutive pairs (B, 2)."""
        jac, resid = np.asarray(jac), np.asarray(resid)
        segments = np.asarray(segments)
        gram = np.matmul(jac.transpose(0, 2, 1), jac)  # the BLAS: 7x an einsum's speed
        if not self.dense:  # first: a block it refuses leaves the equations as they were
            self.arrow.add(gram, segments)
        grads = np.einsum("brc,br->bc", jac, resid)
        self._grad = None
        self.cost += float(np.sum(resid**2))
        index, where = _unknowns(self.p, self.n, self.size, segments)
        self.grad_index.append(index)
        self.grads.append(grads.ravel())
        if self.dense:
            self.where.append(where)
            self.vals.append(gram.ravel())

    @property
    def grad(self):
        """J^T r, summed over the blocks in the order they were added."""
        if self._grad is None:
            self._grad = np.zeros(self.size) if not self.grad_index else np.bincount(
                np.concatenate(self.grad_index), np.concatenate(self.grads), minlength=self.size)
        return self._grad

    def matrix(self):
        """J^T J: a dense array (at most ``DENSE`` unknowns) or an :class:`ArrowMatrix`."""
        if not self.dense:
            return self.arrow
        if not self.vals:
            return np.zeros((self.size, self.size))
        return np.bincount(np.concatenate(self.where), np.concatenate(self.vals),
                           minlength=self.size * self.size).reshape(self.size, self.size)


class ArrowMatrix:
    """A symmetric matrix over (``p`` coefficients, ``k`` segment starts of ``n`` states)
    held by its blocks: ``border`` (p, p), ``coupling`` (k, n, p) (starts by
    coefficients), ``diag`` (k, n, n) and ``upper`` (k - 1, n, n) (start s by start
    s + 1) of the starts' block-tridiagonal block."""

    def __init__(self, border, coupling, diag, upper):
        self.border, self.coupling, self.diag, self.upper = border, coupling, diag, upper
        self.p, (self.k, self.n) = border.shape[0], diag.shape[:2]
        self.shape = (self.p + self.k * self.n,) * 2

    @classmethod
    def zeros(cls, p, k, n):
        return cls(np.zeros((p, p)), np.zeros((k, n, p)), np.zeros((k, n, n)),
                   np.zeros((max(k - 1, 0), n, n)))

    def add(self, gram, segments):
        """Add Gram blocks (B, P + n m, P + n m) of blocks touching ``segments`` (B, m),
        m = 1 or consecutive pairs (m = 2). Where the blocks' segments increase (as in
        every addition of the refinement) by one compiled loop, else where they are
        distinct by one indexed sum, else by ``np.add.at``: the same sums to the bit."""
        p, n = self.p, self.n
        segments = np.asarray(segments, dtype=np.intp)
        m = segments.shape[1]
        if gram.shape != (len(segments), p + n * m, p + n * m):
            raise ValueError(f"ArrowMatrix.add: Gram blocks of shape {gram.shape} for "
                             f"{len(segments)} blocks of {m} segment(s); expected "
                             f"{(len(segments), p + n * m, p + n * m)}.")
        consecutive, increasing, low, high = _order(segments)
        if not consecutive:
            raise ValueError("ArrowMatrix.add: pairs of segments must be consecutive "
                             f"(s, s + 1); received {segments[:3].tolist()}...")
        if len(segments) and (low < 0 or high + m > self.k):
            raise IndexError(f"ArrowMatrix.add: segments {low}..{high + m - 1} for a matrix "
                             f"of {self.k} segments.")
        # numpy's own sum: its order of summation depends on the shapes (pairwise where
        # the blocks' axis becomes its inner loop)
        self.border += gram[:, :p, :p].sum(axis=0)
        if increasing:  # distinct and in order: one compiled loop
            _arrow_add(self.coupling, self.diag, self.upper, gram, segments, p, n)
            return
        first = segments[:, 0]
        distinct = len(np.unique(first)) == len(first)
        add = _add if distinct else np.add.at
        for j in range(segments.shape[1]):
            rows = slice(p + j * n, p + (j + 1) * n)
            add(self.coupling, first + j, gram[:, rows, :p])
            add(self.diag, first + j, gram[:, rows, rows])
        if segments.shape[1] == 2:
            add(self.upper, first, gram[:, p:p + n, p + n:])

    def diagonal(self):
        return np.concatenate([np.diagonal(self.border),
                               np.diagonal(self.diag, axis1=1, axis2=2).ravel()])

    def toarray(self):
        """The whole matrix, dense."""
        p, k, n = self.p, self.k, self.n
        out = np.zeros(self.shape)
        out[:p, :p] = self.border
        out[p:, :p] = self.coupling.reshape(k * n, p)
        out[:p, p:] = out[p:, :p].T
        starts = out[p:, p:].reshape(k, n, k, n)
        s = np.arange(k)
        starts[s, :, s, :] = self.diag
        starts[s[:-1], :, s[1:], :] = self.upper
        starts[s[1:], :, s[:-1], :] = self.upper.transpose(0, 2, 1)
        return out

    def tosparse(self):
        """The whole matrix, sparse (csc)."""
        p, k, n = self.p, self.k, self.n
        a, b = (x.ravel() for x in np.meshgrid(np.arange(n), np.arange(n), indexing="ij"))
        s = np.arange(k)[:, None]
        u = np.arange(max(k - 1, 0))[:, None]
        rows = [(s * n + a).ravel(), (u * n + a).ravel(), ((u + 1) * n + b).ravel()]
        cols = [(s * n + b).ravel(), ((u + 1) * n + b).ravel(), (u * n + a).ravel()]
        vals = [self.diag.reshape(-1), self.upper.reshape(-1), self.upper.reshape(-1)]
        starts = sps.coo_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                        np.concatenate(cols))),
                                shape=(k * n, k * n))
        coupling = sps.csr_matrix(self.coupling.reshape(k * n, p))
        return sps.bmat([[sps.csr_matrix(self.border), coupling.T], [coupling, starts]],
                        format="csc")

    def starts_solve(self, rhs, damping=None):
        """``(S + diag(damping))^-1 rhs`` for the starts' block S through its banded
        Cholesky factor; raises LinAlgError where it is not positive definite to working
        precision."""
        k, n = self.k, self.n
        band = 2 * n - 1
        rows, cols, src_d, src_u = _band_pattern(k, n)
        packed = np.zeros((band + 1, k * n))
        packed[rows[0], cols[0]] = self.diag.reshape(-1)[src_d]
        if k > 1:
            packed[rows[1], cols[1]] = self.upper.reshape(-1)[src_u]
        if damping is not None:
            packed[band] += damping
        try:
            factor = cholesky_upper(packed)
        except np.linalg.LinAlgError as error:
            raise np.linalg.LinAlgError(f"the starts' block is not positive definite "
                                        f"({error})") from None
        out = solve_upper(factor, np.asarray(rhs, float).reshape(k * n, -1))
        if not np.all(np.isfinite(out)):
            raise np.linalg.LinAlgError("the starts' block did not solve")
        return out

    def solve(self, rhs, damping=None):
        """``(self + diag(damping))^-1 rhs`` by its structure: the starts eliminated
        through their banded block, the coefficients from the ``p x p`` Schur complement;
        by a general sparse LU where the starts' block is not positive definite to
        working precision. As numpy's dense solve: NaN where an entry is not finite
        (a point whose sensitivities overflowed: Levenberg-Marquardt rejects the step);
        raises ``numpy.linalg.LinAlgError`` where the matrix is singular."""
        p = self.p
        columns = np.asarray(rhs, float).reshape(self.shape[0], -1)
        try:
            coupling = self.coupling.reshape(self.k * self.n, p)
            inner = self.starts_solve(np.column_stack([coupling, columns[p:]]),
                                      None if damping is None else damping[p:])
        except np.linalg.LinAlgError:  # the general sparse solver
            if not self._finite(columns, damping):
                return np.full(np.shape(rhs), np.nan)
            matrix = self.tosparse()
            if damping is not None:
                matrix = matrix + sps.diags(damping, format="csc")
            with warnings.catch_warnings():  # singular: an error, as numpy's dense solve
                warnings.simplefilter("error", MatrixRankWarning)
                try:
                    out = spsolve(matrix, columns)
                except MatrixRankWarning:
                    raise np.linalg.LinAlgError("the normal equations are singular") from None
            return np.asarray(out).reshape(np.shape(rhs))
        border = self.border if damping is None else self.border + np.diag(damping[:p])
        schur = border - coupling.T @ inner[:, :p]
        x_free = np.linalg.solve(schur, columns[:p] - coupling.T @ inner[:, p:]) if p else \
            np.zeros((0, columns.shape[1]))
        x_starts = inner[:, p:] - inner[:, :p] @ x_free
        return np.concatenate([x_free, x_starts]).reshape(np.shape(rhs))

    def _finite(self, *others) -> bool:
        """Whether every block, and every array of ``others`` (None: absent), is finite."""
        arrays = (self.border, self.coupling, self.diag, self.upper, *others)
        return all(bool(np.all(np.isfinite(a))) for a in arrays if a is not None)


_UNKNOWNS: dict = {}  # _unknowns' answers: a fit adds the same few blocks hundreds of times


def _unknowns(p, n, size, segments):
    """The unknowns (B * (p + n m),) that blocks touching ``segments`` (B, m) fill (the
    free coefficients, then each segment's starts), and the flat (row * size + col)
    indices (B * (p + n m)^2,) of their Gram entries: read-only arrays, kept."""
    key = (p, n, size, segments.dtype.str, segments.shape, segments.tobytes())
    found = _UNKNOWNS.get(key)
    if found is None:
        b = len(segments)
        idx = np.concatenate([np.broadcast_to(np.arange(p), (b, p)),
                              p + (segments[..., None] * n + np.arange(n)).reshape(b, -1)],
                             axis=1)
        found = (idx.ravel(), (idx[:, :, None] * size + idx[:, None, :]).ravel())
        for a in found:
            a.flags.writeable = False
        if len(_UNKNOWNS) >= 256:
            _UNKNOWNS.clear()
        _UNKNOWNS[key] = found
    return found


def _add(target, index, values):
    """``target[index] += values`` for distinct ``index`` (np.add.at's sum, faster)."""
    target[index] += values


@njit(cache=True, nogil=True)
def _order(segments):
    """Whether every row of ``segments`` (B, m) is one segment or two consecutive ones
    (s, s + 1), whether the rows' first segments increase strictly, and the least and
    the greatest of them (0 and -1 for no rows)."""
    consecutive, increasing = True, True
    low, high = (segments[0, 0], segments[0, 0]) if segments.shape[0] else (0, -1)
    for b in range(segments.shape[0]):
        if segments.shape[1] == 2 and segments[b, 1] != segments[b, 0] + 1:
            consecutive = False
        if b > 0 and segments[b, 0] <= segments[b - 1, 0]:
            increasing = False
        low, high = min(low, segments[b, 0]), max(high, segments[b, 0])
    return consecutive, increasing, low, high


@njit(cache=True, nogil=True)
def _arrow_add(coupling, diag, upper, gram, segments, p, n):
    """The starts' blocks of :meth:`ArrowMatrix.add` (Gram blocks ``gram`` (B, p + n m,
    p + n m) of ``segments`` (B, m) whose first segments increase strictly) in one loop,
    without the array version's small operations (8,000 calls in a discovery over
    20,000 samples), and with its arithmetic to the bit: each entry gets one addition
    per block, every block's first segment before any block's second."""
    n_blocks, m = segments.shape
    for k in range(m):  # a segment is each block's first, then its second: in that order
        r = p + k * n
        for b in range(n_blocks):
            s = segments[b, 0] + k
            for i in range(n):
                for c in range(p):
                    coupling[s, i, c] += gram[b, r + i, c]
                for c in range(n):
                    diag[s, i, c] += gram[b, r + i, r + c]
    if m == 2:
        for b in range(n_blocks):
            for i in range(n):
                for c in range(n):
                    upper[segments[b, 0], i, c] += gram[b, p + i, p + n + c]


@lru_cache(maxsize=32)
def _band_pattern(k, n):
    """Where the entries of the diagonal blocks (upper triangle) and of the upper
    blocks go in LAPACK's upper banded storage (bandwidth 2n - 1) of a k-block
    tridiagonal matrix, and where they come from in the flattened blocks."""
    band = 2 * n - 1
    a, b = np.triu_indices(n)
    s = np.arange(k)[:, None]
    i, j = (s * n + a).ravel(), (s * n + b).ravel()
    src_d = (s * n * n + a * n + b).ravel()
    aa, bb = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    s = np.arange(max(k - 1, 0))[:, None]
    iu, ju = (s * n + aa.ravel()).ravel(), ((s + 1) * n + bb.ravel()).ravel()
    src_u = (s * n * n + aa.ravel() * n + bb.ravel()).ravel()
    out = ((band + i - j, band + iu - ju), (j, ju), src_d, src_u)
    for a in (*out[0], *out[1], src_d, src_u):
        a.flags.writeable = False
    return out


def as_array(matrix):
    """A matrix from :meth:`NormalEquations.matrix` as a dense array."""
    return matrix.toarray() if isinstance(matrix, ArrowMatrix) else matrix


def solve(matrix, rhs, damping=None):
    """Solve ``(matrix + diag(damping)) x = rhs`` for a symmetric positive (semi)definite
    ``matrix``, a dense array or an :class:`ArrowMatrix`; ``matrix`` itself is left as
    it was, so one point's matrix serves all of its damped solves. ``rhs`` may hold
    several columns."""
    if isinstance(matrix, ArrowMatrix):
        return matrix.solve(rhs, damping)
    if damping is not None:
        matrix = matrix.copy()
        matrix[np.diag_indices_from(matrix)] += damping
    return np.linalg.solve(matrix, rhs)
