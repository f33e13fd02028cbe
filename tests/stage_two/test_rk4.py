"""Stage two's fixed-grid Runge-Kutta (``shooting.rk4``): fourth order against an
analytic solution, its slopes, and the in-place numpy path against the textbook
formula, digit for digit."""

import numpy as np
import pytest
import torch

from latentsindy._stage_two.fit.shooting import rk4

ROTATION = np.array([[0.0, 1.0], [-1.0, 0.0]])


def _rotation(y):
    return y @ ROTATION.T if isinstance(y, np.ndarray) else y @ torch.as_tensor(ROTATION).T


def _exact(y0, t):
    c, s = np.cos(t), np.sin(t)
    return np.stack([c * y0[..., 0] + s * y0[..., 1], -s * y0[..., 0] + c * y0[..., 1]], -1)


def _textbook(func, y0, steps):
    """The 3/8 rule written out of place, as torchdiffeq's ``rk4`` step reads."""
    out, y = [y0], y0
    for dt in steps:
        k1 = func(y)
        k2 = func(y + dt * k1 * (1 / 3))
        k3 = func(y + dt * (k2 - k1 * (1 / 3)))
        k4 = func(y + dt * (k1 - k2 + k3))
        y = y + (k1 + 3 * (k2 + k3) + k4) * dt * 0.125
        out.append(y)
    return np.stack(out)


@pytest.mark.parametrize("xp", ["numpy", "torch"])
def test_rk4_is_fourth_order(xp):
    """A rotation over one unit of time: halving the step divides the error by 16
    (between 14 and 18), and the error at 20 steps is below 1e-6."""
    y0 = np.array([[1.0, 0.0], [0.3, -2.0]])
    errors = []
    for n in (20, 40, 80):
        grid = torch.linspace(0.0, 1.0, n + 1, dtype=torch.float64)
        start = y0 if xp == "numpy" else torch.as_tensor(y0)
        z, _ = rk4(_rotation, start, grid)
        z = np.asarray(z)
        errors.append(np.abs(z[-1] - _exact(y0, 1.0)).max())
    assert errors[0] < 1e-6
    for coarse, fine in zip(errors[:-1], errors[1:], strict=True):
        assert 14.0 < coarse / fine < 18.0


def test_rk4_in_numpy_is_the_textbook_formula_digit_for_digit():
    """The in-place path makes the same products and sums in the same order: states
    equal bit for bit to the out-of-place formula, and the slopes are the field at
    every grid point (the last one included), bit for bit; the torch path agrees to
    1e-14. (Steps of 0.3 times the field's rate, as stage two takes them: rounding
    differences in the stages would show in the states.)"""
    rng = np.random.default_rng(0)
    y0 = rng.normal(size=(50, 2))

    def cubic(y):
        return 5.0 * (_rotation(y) - 0.3 * y**3)

    grid = torch.linspace(0.0, 1.9, 31, dtype=torch.float64)  # a step not a power of 2
    z, dz = rk4(cubic, y0, grid)
    steps = np.diff(grid.numpy()).tolist()
    assert np.array_equal(z, _textbook(cubic, y0, steps))
    assert np.array_equal(dz, cubic(z))
    zt, dzt = rk4(cubic, torch.as_tensor(y0), grid)
    np.testing.assert_allclose(zt.numpy(), z, rtol=0, atol=1e-14)
    np.testing.assert_allclose(dzt.numpy(), dz, rtol=0, atol=1e-14)


@pytest.mark.parametrize("xp", ["numpy", "torch"])
def test_rk4_gives_each_row_its_own_steps(xp):
    """A grid (K, G) integrates each row on its own steps; a row's padded steps of
    length zero leave its state as it is: each row ends at its own span's exact
    solution (to 1e-7), and the cache holds the steps once made."""
    y0 = np.array([[1.0, 0.0], [0.0, 1.0]])
    spans, points = (1.0, 0.5), 41
    short = np.linspace(0.0, spans[1], 31)
    grid = torch.as_tensor(np.stack([np.linspace(0.0, spans[0], points),
                                     np.concatenate([short, np.full(points - 31, spans[1])])]))
    cache = {}
    start = y0 if xp == "numpy" else torch.as_tensor(y0)
    z, _ = rk4(_rotation, start, grid, cache)
    z = np.asarray(z)
    for row, span in enumerate(spans):
        np.testing.assert_allclose(z[-1, row], _exact(y0[row], span), atol=1e-7)
    assert np.array_equal(z[30, 1], z[-1, 1])  # the padding left the short row alone
    assert len(cache) == 1 and len(next(iter(cache.values()))) == points - 1
