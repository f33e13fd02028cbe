"""LAPACK's banded Cholesky factorisation and solves (``dpbtrf``, ``dpbtrs``, upper
form), compiled, with LAPACK's arithmetic.

For a band of ``kd <= 64`` diagonals above the main one, LAPACK factorises column by
column (``dpbtf2``): the square root of the diagonal, the row beyond it scaled by its
reciprocal (``dscal``), and a rank-one update of the trailing triangle (``dsyr``, one
``daxpy`` per column). ``dpbtrs`` solves each right-hand side by two triangular solves
(``dtbsv``): forward by dot products (``ddot``), backward by ``daxpy``. These
kernels do the same operations in the same order, with OpenBLAS's SkylakeX
kernels' fused multiply-adds and summation order (:mod:`._band_simd`), so their factors
and solutions are LAPACK's to the bit there (``tests/test_banded.py``), in a fraction of
its time on stage one's bands (14-42 wide): LAPACK's calls to its BLAS kernels cost
more than the arithmetic on such short columns, and the solves here take eight
right-hand sides in one pass over the factor.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ._band_simd import axpy8, backward_row8, forward_row8

MAX_KD = 64  # above, LAPACK factorises by blocks (dpotf2, dtrsm, dsyrk): left to it


@njit(cache=True, nogil=True, error_model="numpy")
def factor_band(band, kd, n):
    """Overwrite the upper band (flattened in Fortran order, ``kd + 1`` rows by ``n``)
    with its Cholesky factor, as ``dpbtf2``; returns LAPACK's ``info`` (0, or the order
    of the leading minor that is not positive definite)."""
    ld = kd + 1
    row = np.zeros(kd + 8)  # row j of the factor beyond the diagonal, from row[7]
    for j in range(n):
        ajj = band[kd + j * ld]
        if ajj <= 0.0:  # as LAPACK: not for NaN
            return j + 1
        ajj = np.sqrt(ajj)
        band[kd + j * ld] = ajj
        kn = min(kd, n - 1 - j)
        if kn > 0:
            scale = 1.0 / ajj
            for t in range(kn):
                at = kd - 1 - t + (j + 1 + t) * ld
                value = band[at] * scale
                band[at] = value
                row[7 + t] = value
            for q in range(kn):  # column j + 1 + q of the trailing triangle: q + 1 rows
                if row[7 + q] != 0.0:
                    # by eight rows up from the diagonal's (the same places at every j:
                    # what one step stores, the next loads whole), the first of them
                    # masked where it reaches above the triangle
                    bottom = kd - 7 + (j + 1 + q) * ld
                    for p in range(0, q + 1, 8):
                        axpy8(band, bottom - p, -row[7 + q], row, q - p, max(0, p + 7 - q))
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def solve_band(band, kd, n, rows, width):
    """Solve ``U'U x = b`` in place for the factor ``band`` (as :func:`factor_band`
    leaves it) and the right-hand sides ``rows`` (flattened ``n x width``, C order,
    ``width`` a multiple of 8), each as ``dpbtrs`` solves it."""
    ld = kd + 1
    for i in range(n):
        length = min(i, kd)
        for g in range(0, width, 8):
            forward_row8(band, kd - length + i * ld, rows, (i - length) * width + g, width,
                         length, band[kd + i * ld])
    for i in range(n - 1, -1, -1):
        length = min(i, kd)
        for g in range(0, width, 8):
            backward_row8(band, kd - length + i * ld, rows, (i - length) * width + g, width,
                          length, band[kd + i * ld])


@njit(cache=True, nogil=True, error_model="numpy")
def factor_solve(band, kd, n, rhs, out):
    """:func:`factor_band` on ``band``, then the right-hand sides ``rhs`` (``n x m``)
    solved into ``out`` (``n x m``); returns ``info`` (``out`` untouched unless 0)."""
    info = factor_band(band, kd, n)
    if info:
        return info
    m = rhs.shape[1]
    width = -(-m // 8) * 8
    rows = np.zeros(n * width)
    for i in range(n):
        for c in range(m):
            rows[i * width + c] = rhs[i, c]
    solve_band(band, kd, n, rows, width)
    for c in range(m):
        for i in range(n):
            out[i, c] = rows[i * width + c]
    return 0


@njit(cache=True, nogil=True, error_model="numpy")
def penalised(base, at, scale, which, values, kd, diagonal):
    """A copy of the band ``base`` (flattened) with ``scale[which] * values`` added at
    ``at`` and then ``diagonal`` added to its main diagonal (row ``kd``): numpy's
    ``band[at] += scale[which] * values; band[kd] += diagonal``, in one pass."""
    band = base.copy()
    for k in range(at.shape[0]):
        band[at[k]] += scale[which[k]] * values[k]
    for k in range(kd, band.shape[0], kd + 1):
        band[k] += diagonal
    return band
