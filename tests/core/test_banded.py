"""The direct LAPACK banded Cholesky: scipy's results to the bit, and its errors."""

import numpy as np
import pytest
from scipy.linalg import cho_solve_banded, cholesky_banded

from latentsindy._core.banded import cholesky_upper, solve_upper


def _band(n, w, seed=0):
    rng = np.random.default_rng(seed)
    band = rng.normal(size=(w + 1, n)) * 0.3
    band[-1] = np.abs(band[-1]) + w + 1.0  # diagonally dominant: positive definite
    return band


@pytest.mark.parametrize("n, w", [(1, 0), (50, 3), (700, 24)])
def test_factor_and_solves_are_scipys_to_the_bit(n, w):
    band = _band(n, w)
    factor = cholesky_upper(band)
    np.testing.assert_array_equal(factor, cholesky_banded(band, check_finite=False))
    rhs = np.random.default_rng(1).normal(size=(n, 3))
    for b in (rhs, rhs[:, 0]):
        np.testing.assert_array_equal(
            solve_upper(factor, b), cho_solve_banded((factor, False), b, check_finite=False))


def test_a_matrix_that_is_not_positive_definite_raises():
    band = _band(10, 1)
    band[-1, 4] = -1.0
    with pytest.raises(np.linalg.LinAlgError, match="5-th leading minor not positive"):
        cholesky_upper(band)


def test_no_right_hand_sides_come_back_as_they_are():
    rhs = np.zeros((10, 0))
    assert solve_upper(cholesky_upper(_band(10, 2)), rhs) is rhs


def test_right_hand_sides_of_another_length_are_refused():
    factor = cholesky_upper(_band(6, 1))
    with pytest.raises(ValueError, match="7 rows for a factor of 6 unknowns"):
        solve_upper(factor, np.ones(7))


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
