"""Banded Cholesky factorisation and solves: LAPACK's (``dpbtrf``, ``dpbtrs``, upper
form), with LAPACK's numbers.

Bands up to 64 diagonals above the main one go through the compiled kernels of
:mod:`._band_kernels`, which do LAPACK's operations in its order: the same factor and
solutions to the bit where OpenBLAS runs its SkylakeX (AVX-512) kernels, as on the
machine the benchmarks are measured on (every number; a NaN where LAPACK has one), and
on every machine the same numbers. Wider
bands go to LAPACK itself, with the arguments of ``scipy.linalg.cholesky_banded`` and
``cho_solve_banded`` (``check_finite=False``). Either way there are none of scipy's
per-call validation and batching layers (up to half of a call's time on the small
bands of stage one's evidence, which the structure search evaluates tens of thousands
of times). Float64 only (other dtypes are cast to it, where scipy would keep single
precision): the callers build their bands themselves.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.lapack import dpbtrf, dpbtrs

from ._band_kernels import MAX_KD, factor_band, factor_solve, solve_columns


def _compiled(ab) -> bool:
    """Whether a band goes to the compiled kernels: 1 to ``MAX_KD + 1`` rows (LAPACK's
    unblocked path); others, and malformed ones, to LAPACK itself."""
    return ab.ndim == 2 and 1 <= ab.shape[0] <= MAX_KD + 1


def _own(ab) -> bool:
    """Whether ``ab`` can be factorised in place: writable Fortran-ordered float64."""
    return ab.dtype == np.float64 and ab.flags.f_contiguous and ab.flags.writeable


def cholesky_upper(ab: np.ndarray, overwrite: bool = False) -> np.ndarray:
    """Upper banded Cholesky factor of the float64 band ``ab`` (scipy's layout); raises
    ``numpy.linalg.LinAlgError`` where the matrix is not positive definite.

    The factor is computed in Fortran order (LAPACK's). With ``overwrite`` and a
    Fortran-ordered float64 ``ab``, it is written over ``ab`` itself, with no copy: the
    same numbers in, the same factor out."""
    if not _compiled(ab):
        factor, info = dpbtrf(ab, lower=0, overwrite_ab=overwrite)
    else:
        own = overwrite and _own(ab)
        factor = ab if own else np.array(ab, dtype=np.float64, order="F")
        info = factor_band(factor.reshape(-1, order="F"), factor.shape[0] - 1,
                           factor.shape[1])
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor not positive definite")
    if info < 0:
        raise ValueError(f"illegal value in {-info}-th argument of dpbtrf")
    return factor


def solve_upper(factor: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``A^-1 rhs`` from the upper banded Cholesky factor of ``A`` (``rhs``: a vector or
    a matrix of right-hand sides, solved each as ``dpbtrs`` solves it; the solution in
    Fortran order, as LAPACK's; returned unchanged when empty)."""
    if rhs.shape[0] != factor.shape[1]:
        raise ValueError(f"the right-hand sides have {rhs.shape[0]} rows for a factor of "
                         f"{factor.shape[1]} unknowns; pass one row per unknown.")
    if rhs.size == 0:
        return rhs
    kd, n = factor.shape[0] - 1, factor.shape[1]
    if not _compiled(factor):
        solution, info = dpbtrs(factor, rhs, lower=0)
        if info != 0:
            raise ValueError(f"illegal value in {-info}-th argument of dpbtrs")
        return solution
    factor = np.asarray(factor, dtype=np.float64, order="F")
    columns = np.asarray(rhs, dtype=np.float64).reshape(n, -1)
    solution = np.empty(columns.shape, order="F")
    solve_columns(factor.reshape(-1, order="F"), kd, n, columns, solution)
    return solution[:, 0].copy() if rhs.ndim == 1 else solution


def cholesky_solve(ab: np.ndarray, rhs: np.ndarray, overwrite: bool = False):
    """:func:`cholesky_upper` of ``ab`` and :func:`solve_upper` of the right-hand sides
    ``rhs`` (a matrix) in one call: ``(factor, solution)``, the same numbers."""
    if ab.ndim == 2 and rhs.shape[0] != ab.shape[1]:
        raise ValueError(f"the right-hand sides have {rhs.shape[0]} rows for a band of "
                         f"{ab.shape[1]} unknowns; pass one row per unknown.")
    if not _compiled(ab) or rhs.ndim != 2 or rhs.size == 0:
        factor = cholesky_upper(ab, overwrite)
        return factor, solve_upper(factor, rhs)
    own = overwrite and _own(ab)
    factor = ab if own else np.array(ab, dtype=np.float64, order="F")
    solution = np.empty(rhs.shape, order="F")
    info = factor_solve(factor.reshape(-1, order="F"), factor.shape[0] - 1, factor.shape[1],
                        np.asarray(rhs, dtype=np.float64), solution)
    if info > 0:
        raise np.linalg.LinAlgError(f"{info}-th leading minor not positive definite")
    return factor, solution
