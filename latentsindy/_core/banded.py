"""Banded Cholesky factorisation and solves, straight through LAPACK.

The same LAPACK routines (``dpbtrf``, ``dpbtrs``) and arguments as
``scipy.linalg.cholesky_banded`` and ``cho_solve_banded`` with ``check_finite=False``,
so the results are the same to the bit, without the per-call validation and batching
layers (up to half of a call's time on the small bands of stage one's evidence, which
the structure search evaluates tens of thousands of times). Upper form only, float64
only (other dtypes are cast to it, where scipy would keep single precision): the
callers build their bands themselves.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dpbtrf, dpbtrs


def cholesky_upper(ab: np.ndarray, overwrite: bool = False) -> np.ndarray:
    """Upper banded Cholesky factor of the float64 band ``ab`` (scipy's layout); raises
    ``numpy.linalg.LinAlgError`` where the matrix is not positive definite.

    LAPACK reads the band in Fortran order: a C-ordered band is transposed into a copy
    first (a third of the factorisation's time on a band 77 wide). With ``overwrite``
    and a Fortran-ordered float64 ``ab``, the factor is written over ``ab`` itself, with
    no copy: the same numbers in, the same factor out."""
    factor, info = dpbtrf(ab, lower=0, overwrite_ab=overwrite)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor not positive definite")
    if info < 0:
        raise ValueError(f"illegal value in {-info}-th argument of dpbtrf")
    return factor


def solve_upper(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``A^-1 rhs`` from the upper banded Cholesky factor of ``A`` (``rhs``: a vector or
    a matrix of right-hand sides; returned unchanged when empty)."""
    if rhs.shape[0] != factor.shape[1]:
        raise ValueError(f"the right-hand sides have {rhs.shape[0]} rows for a factor of "
                         f"{factor.shape[1]} unknowns; pass one row per unknown.")
    if rhs.size == 0:
        return rhs
    solution, info = dpbtrs(factor, rhs, lower=0)
    if info != 0:
        raise ValueError(f"illegal value in {-info}-th argument of dpbtrs")
    return solution
