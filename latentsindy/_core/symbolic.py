"""Sympy equations built from coefficients and library structure, and their callables."""

from __future__ import annotations

import numpy as np
import sympy as sp
import torch


class VectorField:
    """The closed system ``d state/dt = rhs(state)`` as a fast callable.

    Call with a numpy array or a torch tensor of shape (..., n_states); ``t`` is
    accepted (and ignored: the system is autonomous) for solver compatibility.

    Examples
    --------
    >>> import sympy as sp
    >>> x, h = sp.symbols("x h", real=True)
    >>> f = VectorField([x, h], [x * h, -h])
    >>> f(0.0, np.array([2.0, 3.0]))
    array([ 6., -3.])
    """

    def __init__(self, symbols, expressions):
        self.symbols = tuple(symbols)
        self.expressions = tuple(expressions)
        self._np = sp.lambdify(self.symbols, list(self.expressions), modules="numpy")
        self._torch = sp.lambdify(self.symbols, list(self.expressions), modules="torch")

    def __call__(self, t, y):
        if torch.is_tensor(y):
            cols = self._torch(*torch.unbind(y, dim=-1))
            return torch.stack([_broadcast_torch(c, y) for c in cols], dim=-1)
        y = np.asarray(y, dtype=float)
        if y.ndim == 1:  # one state, as a solver asks: scalars in, no broadcasting
            return np.array(self._np(*y), dtype=float)  # (18 -> 2 us a call)
        cols = self._np(*np.moveaxis(y, -1, 0))
        return np.stack([np.broadcast_to(np.asarray(c, dtype=float), y.shape[:-1])
                         for c in cols], axis=-1)


def _broadcast_torch(value, like):
    if torch.is_tensor(value):
        return value.expand(like.shape[:-1])
    return torch.full(like.shape[:-1], float(value), dtype=like.dtype, device=like.device)
