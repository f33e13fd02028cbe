"""The posterior spread of a varying-coefficient fit (:mod:`.vcm_fit`): the spline
coefficients' banded covariance and the effective degrees of freedom, computed when
first asked for.

The spread is an object, not a closure over the solver's state, so that a fit pickles:
the structure search (:mod:`.structure`) evaluates a step's neighbours in a helper
process too, and their fits come back pickled.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np

from .vcm import ORDER


class Spread:
    """The spread of one solved structure (the solver's pieces, kept)."""

    def __init__(self, st, solved, m_knots, rough, weights, s2, ridge, uniform):
        self.st, self.solved, self.m_knots = st, solved, m_knots
        self.rough, self.weights, self.s2 = rough, weights, s2
        self.ridge, self.uniform = ridge, uniform
        self.cov = None

    def covariance(self):
        """Per unit noise variance (computed once)."""
        if self.cov is None:
            self.cov = covariance(self.st, self.solved, self.m_knots)
        return self.cov

    def spline_cov(self):
        return self.covariance() * self.s2

    def edf(self):
        """Effective degrees of freedom per varying term: knots - tr(Sigma R)."""
        cov = self.covariance()
        m_knots, v = cov.shape[1], cov.shape[2]
        out = np.zeros(v)
        for a in range(v):
            pen = (self.uniform if self.weights[a] is None
                   else penalty_band(self.weights[a], m_knots))
            trace = self.ridge * float(np.sum(cov[0, :, a]))
            for d in range(3):
                trace += (2.0 if d else 1.0) * self.rough[a] * float(
                    np.sum(pen[2 - d, d:] * cov[d, : m_knots - d, a]))
            out[a] = m_knots - trace
        return out


class NoSpread:
    """The spread of a structure that could not be solved: zeros."""

    def __init__(self, m_knots, v):
        self.m_knots, self.v = m_knots, v

    def spline_cov(self):
        return np.zeros((ORDER, self.m_knots, self.v))

    def edf(self):
        return np.zeros(self.v)


def covariance(st, solved, m_knots):
    """Covariance (per unit noise variance) of each varying term's spline
    coefficients m and m + d, d < 4: (4, n_knots, v)."""
    u, proj, schur_inv = solved[1][:3]
    v = len(st.varying)
    cov = np.zeros((ORDER, m_knots, v))
    if not v:
        return cov
    inv = selected_inverse(u)
    for a in range(v):
        for d in range(ORDER):
            cols = np.arange(d, m_knots) * v + a
            entry = inv[st.width - 1 - d * v, cols]
            if len(st.constant):  # the constants' share of the covariance
                rows = np.arange(0, m_knots - d) * v + a
                entry = entry + np.einsum("ij,jk,ik->i", proj[rows], schur_inv, proj[cols])
            cov[d, : m_knots - d, a] = entry
    return cov


def penalty_band(q, n_knots):
    """Upper band (3, n_knots) of D2' diag(q) D2 in scipy's layout (row 2 - d, column j
    holds element (j - d, j)); D2 takes second differences."""
    qq = np.zeros(n_knots + 2)
    qq[2:n_knots] = q  # qq[i + 2] = q_i
    j = np.arange(n_knots)
    off1 = np.zeros(n_knots)
    off1[1:] = -2.0 * (qq[j[1:] + 1] + qq[j[1:]])
    off2 = np.zeros(n_knots)
    off2[2:] = qq[j[2:]]
    return np.stack([off2, off1, qq[j + 2] + 4 * qq[j + 1] + qq[j]])


def selected_inverse(u: np.ndarray) -> np.ndarray:
    """Entries of A^-1 inside the band of A = U'U, from its upper banded Cholesky factor
    ``u`` (scipy's layout), in the same layout (zeros outside the matrix); the entries
    of ``u`` outside the matrix (its unused corner) do not matter.

    Takahashi's recursion by blocks: cut the unknowns into blocks of b >= w (the
    bandwidth), so that U is block bidiagonal with upper triangular diagonal blocks
    D_I and couplings C_I. From U Sigma = U^-T, block row I gives

        Sigma_{I,I+1} = -Y_I Sigma_{I+1,I+1},
        Sigma_{I,I}   = P_I + Y_I Sigma_{I+1,I+1} Y_I',

    with Y_I = D_I^-1 C_I and P_I = D_I^-1 D_I^-T, computed for every block at once.
    C_I has w nonzero columns, so the only step taken block by block carries the
    w x w corner of Sigma_{I+1,I+1}; the rest is again computed for all blocks at once.
    O(ceil(n / b) b^3) work in batched products (b = w for bands of 16 and wider, so
    about 5 n w^2, against n w^2 / 2 for the factorisation), ceil(n / b) steps of
    w x w products."""
    width, n = u.shape
    w = width - 1
    if w == 0 or n == 0:
        return 1.0 / u**2
    block = w * max(1, -(-_MIN_BLOCK // w))
    n_blocks = -(-n // block)
    padded = np.zeros((width, (n_blocks + 1) * block))  # the identity past the end
    padded[:, :n] = u
    padded[w, n:] = 1.0
    blocks = padded.reshape(width, n_blocks + 1, block)  # [row, block, column in it]
    pick = _block_patterns(w, block)
    # D_I[p, q] = U[Ib + p, Ib + q]; C_I: rows b - w.. of block I, columns ..w of I + 1
    d = np.where(pick.d_in, np.moveaxis(blocks[pick.d_rows, :n_blocks, pick.d_cols], -1, 0),
                 0.0)
    c = np.where(pick.c_in, np.moveaxis(blocks[pick.c_rows, 1:, pick.c_cols], -1, 0), 0.0)
    d_inv = np.linalg.inv(d)  # (blocks, b, b), upper triangular
    diagonal = d_inv @ np.swapaxes(d_inv, 1, 2)  # P_I, then Sigma_{I,I}
    y = d_inv[:, :, block - w:] @ c  # (blocks, b, w): C_I's nonzero columns
    corner = np.empty((n_blocks, w, w))  # Sigma_{I,I}'s top left w x w
    corner[-1] = s = diagonal[-1, :w, :w]
    for i in range(n_blocks - 2, -1, -1):
        top = y[i, :w]
        s = diagonal[i, :w, :w] + top @ s @ top.T
        corner[i] = s
    diagonal[:-1] += y[:-1] @ corner[1:] @ np.swapaxes(y[:-1], 1, 2)
    coupling = -(y[:-1, block - w:] @ corner[1:])  # Sigma_{I,I+1}'s corner that matters
    # output row w - k, column Ib + q: Sigma[Ib + q - k, Ib + q], from block I's diagonal
    # block where q >= k, else from the coupling of block I - 1
    out = np.where(pick.inside, diagonal[:, pick.o_rows, pick.o_cols], 0.0)
    out[1:] += np.where(pick.below, coupling[:, pick.r_rows, pick.r_cols], 0.0)
    return np.moveaxis(out, 0, 1).reshape(width, n_blocks * block)[:, :n]


_MIN_BLOCK = 16  # rows per block at least: fewer block steps on narrow bands


class _Patterns(NamedTuple):
    d_rows: np.ndarray
    d_cols: np.ndarray
    d_in: np.ndarray
    c_rows: np.ndarray
    c_cols: np.ndarray
    c_in: np.ndarray
    o_rows: np.ndarray
    o_cols: np.ndarray
    inside: np.ndarray
    r_rows: np.ndarray
    r_cols: np.ndarray
    below: np.ndarray


@functools.lru_cache(maxsize=16)
def _block_patterns(w, block):
    """Where :func:`selected_inverse` reads within a block (the same for every block):
    the band rows and columns of D_I and C_I, and the output's sources (b x b index
    arrays at most, whatever the number of unknowns)."""
    p, q = np.arange(block)[:, None], np.arange(block)[None, :]
    off = q - p  # D_I[p, q] = band[w - off, Ib + q]
    d_in = (off >= 0) & (off <= w)
    pc, qc = np.arange(w)[:, None] + (block - w), np.arange(w)[None, :]
    off_c = block + qc - pc  # C_I[pc, qc] = band[w - off_c, (I + 1) b + qc]
    c_in = off_c <= w
    k, col = np.arange(w, -1, -1)[:, None], np.arange(block)[None, :]
    inside = col - k >= 0
    patterns = _Patterns(np.where(d_in, w - off, 0), np.broadcast_to(q, off.shape), d_in,
                         np.where(c_in, w - off_c, 0), np.broadcast_to(qc, off_c.shape),
                         c_in, np.where(inside, col - k, 0),
                         np.broadcast_to(col, inside.shape), inside,
                         np.where(inside, 0, w + col - k), np.where(inside, 0, col), ~inside)
    for array in patterns:  # shared by every call of this shape: never written
        array.setflags(write=False)
    return patterns
