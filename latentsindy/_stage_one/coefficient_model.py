"""The coefficient model of stage one (timeVAE's; ``sequential_model`` extends it) and
the constant fit it starts from."""

from __future__ import annotations

import torch
from torch import nn


class CoefficientModel(nn.Module):
    """Xi(t) = support * (constants + time_varying * generator(x)), normalised units.

    A constant can be pinned (:meth:`pin_constant`): it then keeps its value whatever
    the optimiser does (the exact model's estimate, see ``decisions.adopt_structure``).
    """

    def __init__(self, generator, constants, support, time_varying):
        super().__init__()
        self.generator = generator
        self.constants = nn.Parameter(constants.clone())
        self.register_buffer("support", support.clone())
        self.register_buffer("time_varying", time_varying.clone())
        self.register_buffer("pin_mask", torch.zeros_like(support, dtype=torch.bool))
        self.register_buffer("pin_value", torch.zeros_like(constants))
        self.restored = []  # (equation, term) pairs returned by restore_terms

    def effective_constants(self) -> torch.Tensor:
        """The constants, pinned ones replaced by their pinned values."""
        return torch.where(self.pin_mask, self.pin_value, self.constants)

    @torch.no_grad()
    def pin_constant(self, i: int, j: int, value: float) -> None:
        """Fit term ``j`` of equation ``i`` as the constant ``value``, not trained."""
        self.time_varying[i, j] = 0.0
        self.pin_mask[i, j] = True
        self.pin_value[i, j] = value
        self.constants[i, j] = value

    @torch.no_grad()
    def mean_blocks(self, inputs):
        """Yield (start, stop, Xi) with Xi (stop - start, n, F): the mean coefficients
        over the whole series, block by block."""
        xi, _ = self(inputs, 0)
        yield 0, xi.shape[1], xi[0]

    @torch.no_grad()
    def restore_constant(self, i: int, j: int) -> None:
        """Put term ``j`` of equation ``i`` back in the support, as a constant."""
        self.support[i, j] = True
        self.time_varying[i, j] = 0.0

    @torch.no_grad()
    def freeze_constant(self, i: int, j: int, value: float) -> None:
        """Fit term ``j`` of equation ``i`` as the constant ``value`` from now on."""
        self.time_varying[i, j] = 0.0
        self.constants[i, j] = value

    @torch.no_grad()
    def free_variation(self, i: int, j: int) -> None:
        """Let term ``j`` of equation ``i`` vary."""
        self.time_varying[i, j] = 1.0

    def forward(self, inputs, n_samples: int):
        series, kl = self.generator.sample(inputs, n_samples)
        n_states, n_features = self.constants.shape
        series = series.reshape(series.shape[0], series.shape[1], n_states, n_features)
        xi = self.support * (self.effective_constants() + self.time_varying * series)
        return xi, kl


def least_squares_constants(theta, xdot, support):
    """Constant-coefficient fit per equation on its support (normalised, small ridge)."""
    n_states, n_features = support.shape
    a = theta.reshape(-1, n_features)
    b = xdot.reshape(-1, n_states)
    out = torch.zeros(n_states, n_features, dtype=theta.dtype, device=theta.device)
    for i in range(n_states):
        cols = torch.nonzero(support[i]).flatten()
        if len(cols) == 0:
            continue
        ai = a[:, cols]
        gram = ai.T @ ai + 1e-6 * a.shape[0] * torch.eye(len(cols), dtype=a.dtype,
                                                         device=a.device)
        out[i, cols] = torch.linalg.solve(gram, ai.T @ b[:, i])
    return out
