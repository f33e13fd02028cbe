"""The closed system's callable: one state, many states and torch agree."""

import numpy as np
import sympy as sp
import torch

from latentsindy._core.symbolic import VectorField


def _field():
    x, h = sp.symbols("x h", real=True)
    # a constant and a zero right-hand side come out of lambdify as plain numbers
    return VectorField([x, h, sp.Symbol("c")], [1.2 * x - 0.5 * x * h, sp.Float(0.25),
                                               sp.Integer(0)])


def test_one_state_is_a_row_of_many_states_to_the_bit():
    field = _field()
    states = np.random.default_rng(0).normal(size=(50, 3))
    many = field(0.0, states)
    assert many.shape == (50, 3) and many.dtype == float
    rows = np.array([field(0.0, s) for s in states])
    assert rows.shape == (50, 3) and rows.dtype == float
    assert np.array_equal(rows, many)
    assert np.array_equal(many[:, 1:], np.tile([0.25, 0.0], (50, 1)))
    np.testing.assert_allclose(field(0.0, [1.0, 2.0, 3.0]), [0.2, 0.25, 0.0], rtol=1e-15)


def test_torch_states_give_the_numpy_values():
    field = _field()
    states = np.random.default_rng(1).normal(size=(2, 4, 3))
    got = field(0.0, torch.as_tensor(states))
    assert got.shape == (2, 4, 3)
    np.testing.assert_allclose(got.numpy(), field(0.0, states), rtol=1e-15)
