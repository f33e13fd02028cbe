"""The normal equations of multiple shooting (J^T J and J^T r over the free
coefficients and the segments' starts) and their solution.

They have an arrow structure (coefficients couple everything, each start couples only
its own segment and its neighbours), so they are assembled block by block; up to
``DENSE`` unknowns (a few hundred: every benchmark family at 2,000 samples) they are
held and solved densely, which costs least there, and beyond it sparsely, the starts'
banded block factorized on its own (:func:`_bordered_solve`): memory and time grow
with the number of segments, not with its square.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.sparse.linalg import spsolve

# normal equations with up to this many unknowns are assembled and solved densely
# (LAPACK), larger ones sparsely
DENSE = 600


class NormalEquations:
    """Block assembly of J^T J and J^T r for (free coefficients, segment starts): a dense
    array when the system has at most ``DENSE`` unknowns, else a sparse matrix."""

    def __init__(self, n_free, n_segments, n_states):
        self.p, self.k, self.n = n_free, n_segments, n_states
        self.size = n_free + n_segments * n_states
        self.dense = self.size <= DENSE
        # per added block: the unknowns its gradient entries go to and those entries;
        # where its Gram entries go (flat row * size + col indices when dense, a (2, N)
        # stack of rows and columns when sparse) and those entries
        self.grad_index, self.grads, self.where, self.vals = [], [], [], []
        self.cost, self._grad = 0.0, None

    def add(self, jac, resid, segments):
        """Rows ``jac`` (B, R, P + n * len(segments)) for the residuals ``resid`` (B, R)
        of the blocks whose starts are ``segments`` (B, len(segments))."""
        jac, resid = np.asarray(jac), np.asarray(resid)
        gram = np.matmul(jac.transpose(0, 2, 1), jac)  # the BLAS: 7x an einsum's speed
        self.grads.append(np.einsum("brc,br->bc", jac, resid).ravel())
        self._grad = None
        self.cost += float(np.sum(resid**2))
        idx = np.concatenate([np.broadcast_to(np.arange(self.p), (len(segments), self.p)),
                              self.p + (segments[..., None] * self.n
                                        + np.arange(self.n)).reshape(len(segments), -1)],
                             axis=1)
        self.grad_index.append(idx.ravel())
        if self.dense:
            self.where.append((idx[:, :, None] * self.size + idx[:, None, :]).ravel())
        else:
            self.where.append(np.stack([np.repeat(idx[:, :, None], idx.shape[1], axis=2).ravel(),
                                        np.repeat(idx[:, None, :], idx.shape[1], axis=1).ravel()]))
        self.vals.append(gram.ravel())

    @property
    def grad(self):
        """J^T r, summed over the blocks in the order they were added."""
        if self._grad is None:
            self._grad = np.zeros(self.size) if not self.grad_index else np.bincount(
                np.concatenate(self.grad_index), np.concatenate(self.grads), minlength=self.size)
        return self._grad

    def matrix(self):
        """J^T J: a dense array (at most ``DENSE`` unknowns) or a sparse csc matrix."""
        if not self.vals:
            return np.zeros((self.size, self.size)) if self.dense else sps.csc_matrix(
                (self.size, self.size))
        if self.dense:  # entries summed in the order they were added
            return np.bincount(np.concatenate(self.where), np.concatenate(self.vals),
                               minlength=self.size * self.size).reshape(self.size, self.size)
        rows, cols = np.concatenate(self.where, axis=1)
        return sps.csc_matrix((np.concatenate(self.vals), (rows, cols)),
                              shape=(self.size, self.size))


def as_array(matrix):
    """A matrix from :meth:`NormalEquations.matrix` as a dense array."""
    return matrix.toarray() if sps.issparse(matrix) else matrix


def solve(matrix, rhs, damping=None, border=None):
    """Solve ``(matrix + diag(damping)) x = rhs`` for a symmetric positive (semi)definite
    ``matrix``, a dense array or sparse (solved densely when small); ``matrix`` itself
    is left as it was, so one point's matrix serves all of its damped solves. ``rhs``
    may hold several columns. With ``border`` (the number of free coefficients, which
    come first) a large sparse matrix is solved by :func:`_bordered_solve`."""
    if sps.issparse(matrix) and matrix.shape[0] <= DENSE:
        matrix = matrix.toarray()
    if isinstance(matrix, np.ndarray):
        if damping is not None:
            matrix = matrix.copy()
            matrix[np.diag_indices_from(matrix)] += damping
        return np.linalg.solve(matrix, rhs)
    if damping is not None:
        matrix = matrix + sps.diags(damping, format="csc")
    if border is not None:
        try:
            return _bordered_solve(matrix, np.asarray(rhs, float), border)
        except (np.linalg.LinAlgError, ValueError):
            pass  # not positive definite to working precision (or not finite): the
            # general solver
    return spsolve(matrix, rhs)


# starts' blocks banded more widely than this are solved by the general sparse solver
MAX_BAND = 64


def _bordered_solve(matrix, rhs, p):
    """The normal equations of multiple shooting, with their structure: the free
    coefficients (the first ``p`` unknowns) touch everything, but a segment's start
    only touches its own and its neighbours' (continuity), so the starts' block is
    banded. A banded Cholesky factorization of that block and the ``p x p`` Schur
    complement cost O(segments), where a general sparse LU of the bordered matrix grew
    much faster (4 ms a solve at 400 segments). Raises LinAlgError where the block is
    not positive definite or is banded more widely than :data:`MAX_BAND`."""
    factor = banded_factor(matrix[p:, p:])
    coupling = matrix[p:, :p].toarray()
    columns = rhs.reshape(len(rhs), -1)
    inner = cho_solve_banded(factor, np.column_stack([coupling, columns[p:]]))
    schur = matrix[:p, :p].toarray() - coupling.T @ inner[:, :p]
    x_free = np.linalg.solve(schur, columns[:p] - coupling.T @ inner[:, p:]) if p else \
        np.zeros((0, columns.shape[1]))
    x_starts = inner[:, p:] - inner[:, :p] @ x_free
    return np.concatenate([x_free, x_starts]).reshape(rhs.shape)


def banded_factor(matrix):
    """The banded Cholesky factor of a sparse symmetric positive definite ``matrix``
    (for ``scipy.linalg.cho_solve_banded``); raises LinAlgError where it is banded more
    widely than :data:`MAX_BAND` or is not positive definite to working precision."""
    coo = matrix.tocoo()
    upper = coo.row <= coo.col
    band = int(np.max(coo.col[upper] - coo.row[upper], initial=0))
    if band > MAX_BAND:
        raise np.linalg.LinAlgError("not banded")
    packed = np.zeros((band + 1, coo.shape[0]))
    np.add.at(packed, (band + coo.row[upper] - coo.col[upper], coo.col[upper]),
              coo.data[upper])
    return cholesky_banded(packed), False
