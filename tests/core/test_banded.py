"""The banded Cholesky factorisation and solves: LAPACK's numbers, and its errors.

Bands up to 64 diagonals above the main one (65 wide) go through compiled kernels that
do LAPACK's operations in its order with OpenBLAS's SkylakeX kernels' arithmetic: where
scipy's OpenBLAS runs those kernels (the benchmark machine), the factor and solutions
are LAPACK's to the bit; elsewhere they agree to rounding.
"""

import re

import numpy as np
import pytest
from scipy.linalg import cho_solve_banded, cholesky_banded
from threadpoolctl import threadpool_info

import latentsindy._core.banded as banded
from latentsindy._core._band_kernels import MAX_KD, penalised
from latentsindy._core.banded import cholesky_solve, cholesky_upper, solve_upper

_AVX512_KERNELS = {"SkylakeX", "Cooperlake", "SapphireRapids"}  # one ddot, one daxpy


def _skylakex() -> bool:
    import scipy.linalg  # noqa: F401  (loads scipy's OpenBLAS)

    return any(i.get("internal_api") == "openblas" and "scipy.libs" in i["filepath"]
               and i.get("architecture") in _AVX512_KERNELS for i in threadpool_info())


def _check_same(ours, lapack):
    """To the bit on LAPACK's own kernels (signed zeros too; NaN where LAPACK has
    NaN); to rounding elsewhere."""
    assert ours.shape == lapack.shape
    if not _skylakex():
        np.testing.assert_allclose(ours, lapack, rtol=1e-10, atol=1e-300)
    elif np.isnan(lapack).any():
        np.testing.assert_array_equal(ours, lapack)
    else:
        np.testing.assert_array_equal(np.ascontiguousarray(ours).view(np.int64),
                                      np.ascontiguousarray(lapack).view(np.int64))


def _band(n, w, seed=0):
    rng = np.random.default_rng(seed)
    band = rng.normal(size=(w + 1, n)) * 0.3
    band[-1] = np.abs(band[-1]) + w + 1.0  # diagonally dominant: positive definite
    return band


def _random_band(rng):
    """A positive definite band of random width, size and scale, some entries zero;
    or, now and then, one that is not positive definite."""
    kd = int(rng.integers(0, MAX_KD + 1))
    n = int(rng.integers(1, 200))
    band = np.zeros((kd + 1, n))
    band[:kd] = rng.standard_normal((kd, n)) * 10.0 ** rng.uniform(-3, 3)
    band[:kd][rng.uniform(size=(kd, n)) < rng.uniform(0, 0.4)] = 0.0
    band[kd] = (np.abs(band[:kd]).sum(0) * rng.uniform(0.6, 3)
                + rng.uniform(0, 10, n) * 10.0 ** rng.uniform(-3, 3))
    return band


@pytest.mark.parametrize("n, w", [(1, 0), (50, 3), (700, 24), (300, 70)])
def test_factor_and_solves_are_scipys(n, w):
    """Narrow bands by the compiled kernels, 70 wide by LAPACK itself."""
    band = _band(n, w)
    factor = cholesky_upper(band)
    _check_same(factor, cholesky_banded(band, check_finite=False))
    rhs = np.random.default_rng(1).normal(size=(n, 3))
    for b in (rhs, rhs[:, 0]):
        _check_same(solve_upper(factor, b),
                    cho_solve_banded((factor, False), b, check_finite=False))


def test_random_bands_factor_and_solve_as_lapack():
    """Bands 1-65 wide, 1-200 unknowns, scales over six decades, zeros in the band and
    1-20 right-hand sides (more than the kernels' eight at a time): LAPACK's factor or
    its failing minor, and its solutions."""
    rng = np.random.default_rng(7)
    failed = 0
    for _ in range(150):
        band = _random_band(rng)
        try:
            expected = cholesky_banded(band, check_finite=False)
        except np.linalg.LinAlgError as error:
            failed += 1
            with pytest.raises(np.linalg.LinAlgError, match="^" + re.escape(str(error)) + "$"):
                cholesky_upper(band)
            continue
        factor = cholesky_upper(band)
        _check_same(factor, expected)
        rhs = rng.standard_normal((band.shape[1], int(rng.integers(1, 21))))
        rhs *= 10.0 ** rng.uniform(-3, 3, rhs.shape[1])
        lapack = cho_solve_banded((expected, False), rhs, check_finite=False)
        _check_same(solve_upper(factor, rhs), lapack)
        both = cholesky_solve(np.asfortranarray(band), rhs)
        _check_same(both[0], expected)
        _check_same(both[1], lapack)
    assert 0 < failed < 150  # both kinds of band were drawn


def test_a_matrix_that_is_not_positive_definite_raises():
    band = _band(10, 1)
    band[-1, 4] = -1.0
    for factorise in (cholesky_upper, lambda b: cholesky_solve(b, np.ones((10, 2)))):
        with pytest.raises(np.linalg.LinAlgError, match="5-th leading minor not positive"):
            factorise(band)


def test_a_nan_goes_through_as_lapack_lets_it():
    """LAPACK's test of the pivot (not above zero) lets a NaN pass: so do the kernels."""
    band = _band(10, 2)
    band[-1, 3] = np.nan
    factor = cholesky_upper(band)
    assert np.isnan(factor[-1, 3:]).all() and np.isfinite(factor[-1, :3]).all()
    _check_same(factor, cholesky_banded(band, check_finite=False))


def test_bands_up_to_65_wide_are_compiled_and_wider_ones_go_to_lapack(monkeypatch):
    calls = []
    compiled = banded.factor_band
    monkeypatch.setattr(banded, "factor_band", lambda *a: calls.append(a) or compiled(*a))
    cholesky_upper(_band(200, MAX_KD))
    assert len(calls) == 1
    cholesky_upper(_band(200, MAX_KD + 1))
    assert len(calls) == 1


def test_a_band_of_no_rows_is_refused_by_lapack_not_read_out_of_bounds():
    with pytest.raises(ValueError):
        cholesky_upper(np.zeros((0, 3)))


def test_one_call_factorises_and_solves_without_touching_its_inputs():
    """``cholesky_solve``: the factor and the solutions (Fortran order, as LAPACK's) of
    an integer band, its inputs as they were."""
    band = np.round(_band(60, 5) * 100).astype(int)
    rhs = np.random.default_rng(2).normal(size=(60, 11))
    band_before, rhs_before = band.copy(), rhs.copy()
    factor, solution = cholesky_solve(band, rhs)
    np.testing.assert_array_equal(band, band_before)
    np.testing.assert_array_equal(rhs, rhs_before)
    assert solution.flags.f_contiguous and solution.shape == rhs.shape
    np.testing.assert_array_equal(factor, cholesky_upper(band.astype(float)))
    np.testing.assert_array_equal(solution, solve_upper(factor, rhs))
    _check_same(solution, cho_solve_banded((cholesky_banded(band.astype(float)), False), rhs))


def test_a_read_only_band_is_copied_even_with_overwrite():
    band = np.asfortranarray(_band(30, 4))
    band.flags.writeable = False
    factor = cholesky_upper(band, overwrite=True)
    assert not np.shares_memory(factor, band)
    np.testing.assert_array_equal(factor, cholesky_upper(_band(30, 4)))


def test_no_right_hand_sides_come_back_as_they_are():
    rhs = np.zeros((10, 0))
    assert solve_upper(cholesky_upper(_band(10, 2)), rhs) is rhs


def test_right_hand_sides_of_another_length_are_refused():
    factor = cholesky_upper(_band(6, 1))
    with pytest.raises(ValueError, match="7 rows for a factor of 6 unknowns"):
        solve_upper(factor, np.ones(7))
    with pytest.raises(ValueError, match="7 rows for a band of 6 unknowns"):
        cholesky_solve(_band(6, 1), np.ones((7, 2)))


@pytest.mark.parametrize("n, w", [(1, 0), (50, 3), (700, 24)])
def test_a_fortran_band_is_factorised_in_place_to_the_same_bits(n, w):
    """``overwrite`` on a Fortran-ordered band: no copy (the factor is the band's own
    memory) and the factor of the C-ordered band, bit for bit; without it the band is
    left as it was."""
    band = _band(n, w)
    expected = cholesky_upper(band)
    np.testing.assert_array_equal(band, _band(n, w))
    own = np.asfortranarray(band.copy())
    np.testing.assert_array_equal(cholesky_upper(own), expected)
    np.testing.assert_array_equal(own, band)  # Fortran-ordered, not overwritten either
    factor = cholesky_upper(own, overwrite=True)
    assert np.shares_memory(factor, own)
    np.testing.assert_array_equal(factor, expected)
    own = np.asfortranarray(band.copy())
    factor, _ = cholesky_solve(own, np.ones((n, 2)), overwrite=True)
    assert np.shares_memory(factor, own)
    np.testing.assert_array_equal(factor, expected)


def test_penalties_are_added_as_numpy_adds_them():
    rng = np.random.default_rng(3)
    band = np.asfortranarray(rng.normal(size=(5, 40)))
    at = rng.choice(band.size, 60, replace=False)
    scale, which, values = rng.uniform(1, 1e4, 3), rng.integers(0, 3, 60), rng.normal(size=60)
    expected = band.copy(order="F")
    expected.reshape(-1, order="F")[at] += scale[which] * values
    expected[4] += 0.37
    ours = penalised(band.reshape(-1, order="F"), at, scale, which, values, 4, 0.37)
    np.testing.assert_array_equal(ours.reshape(band.shape, order="F"), expected)
    assert not np.shares_memory(ours, band)
