"""The posterior spread of a varying-coefficient fit (:mod:`.vcm_fit`): the spline
coefficients' banded covariance and the effective degrees of freedom, computed when
first asked for.

The spread is an object, not a closure over the solver's state, so that a fit pickles:
the structure search (:mod:`.structure`) evaluates a step's neighbours in a helper
process too, and their fits come back pickled.
"""

from __future__ import annotations

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


def selected_inverse(u: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Entries of A^-1 inside the band of A = U'U, from its upper banded Cholesky factor
    ``u`` (scipy's layout), in the same layout (Takahashi's recursion: O(n w^2) for n
    unknowns and bandwidth w, never the dense inverse).

    Row i of the inverse's band needs the w x w block of the inverse just below and to
    the right of it. The block is read in place from a dense buffer that holds
    ``chunk`` + w rows and columns of the inverse at a time (entries inside the band of
    the rows computed so far; the rest is stale), so a row copies nothing; when the
    recursion leaves the buffer, the w x w block it still needs is moved up with it,
    once every ``chunk`` rows."""
    if chunk < 1:
        raise ValueError(f"chunk must be a positive number of rows; got {chunk!r}.")
    width, n = u.shape
    w = width - 1
    out = np.zeros_like(u)
    # upper[i, k - 1] = U[i, i + k], k = 1..w (zero past the last unknown)
    upper = np.zeros((n, w))
    for k in range(1, min(w, n - 1) + 1):
        upper[: n - k, k - 1] = u[w - k, k:]
    span = min(chunk + w, n)
    buffer = np.zeros((span, span))  # buffer[p, q] = Sigma[base + p, base + q] in the band
    base = n - span
    right = np.zeros((n, w))  # right[i, k - 1] = Sigma[i, i + k]
    for i in range(n - 1, -1, -1):
        if i < base:  # the buffer moves up by `shift` rows, the block below row i with it
            shift = min(chunk, base)
            block = buffer[:w, :w].copy()
            base -= shift
            buffer[shift:shift + w, shift:shift + w] = block
        m = min(w, n - 1 - i)
        uii = u[w, i]
        row_u = upper[i, :m]
        p = i - base
        window = buffer[p + 1:p + 1 + m, p + 1:p + 1 + m]  # Sigma[i+1 .. i+m] squared
        row = -(row_u @ window) / uii  # Sigma[i, i+1 .. i+m]
        sii = 1.0 / uii**2 - float(row_u @ row) / uii
        out[w, i] = sii
        right[i, :m] = row
        buffer[p, p] = sii
        buffer[p, p + 1:p + 1 + m] = row
        buffer[p + 1:p + 1 + m, p] = row
    for k in range(1, min(w, n - 1) + 1):
        out[w - k, k:] = right[: n - k, k - 1]
    return out
