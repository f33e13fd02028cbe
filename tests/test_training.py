"""The training step that returns pruned terms the data need (a forward step)."""

import numpy as np
import torch
from torch import nn

from latentsindy._training import CoefficientModel, restore_terms


class _Flat(nn.Module):
    """A generator with no time variation (Xi = constants)."""

    def __init__(self, n_out):
        super().__init__()
        self.n_out = n_out

    def sample(self, inputs, n_samples):
        return torch.zeros(max(n_samples, 1), inputs.shape[-1], self.n_out), torch.zeros(())


def _problem(small=-0.5):
    """Normalised library [a, b, c] with b nearly collinear with a; xdot = 2a + small*b."""
    t = np.linspace(0, 20, 2000)
    a = np.sin(t)
    b = np.sin(t) + 0.3 * np.cos(1.3 * t)
    c = np.cos(3.7 * t)
    theta = np.stack([a, b, c], axis=1)
    theta /= np.sqrt(np.mean(theta**2, axis=0))
    truth = np.array([2.0, small, 0.0])
    xdot = theta @ truth
    scale = np.sqrt(np.mean(xdot**2))
    as_t = lambda v: torch.as_tensor(v, dtype=torch.float32)  # noqa: E731
    return (as_t(theta[None]), as_t(xdot[None, :, None] / scale), truth / scale,
            torch.zeros(1, 2, 2000))


def _model(theta, xdot, support):
    support = torch.as_tensor(support)[None]
    a = theta[0][:, support[0]]
    constants = torch.zeros(1, 3)
    constants[0, support[0]] = torch.linalg.lstsq(a, xdot[0]).solution[:, 0]
    return CoefficientModel(_Flat(3), constants, support, torch.ones(1, 3))


def test_collinear_term_is_restored_with_exact_constants():
    """b explains little beyond a, but it is real and above threshold: it returns, and
    the joint refit gives the true constants (1e-4); c, which explains nothing, stays out;
    the restored term is a constant."""
    theta, xdot, truth, inputs = _problem()
    model = _model(theta, xdot, [True, False, False])
    weights = torch.ones_like(xdot)
    restored = restore_terms(model, theta, xdot, weights, inputs, 0.05, torch.tensor([True]))
    assert restored == [(0, 1)]
    assert model.support.tolist() == [[True, True, False]]
    assert model.time_varying.tolist() == [[1.0, 0.0, 1.0]]
    np.testing.assert_allclose(model.constants[0, :2].detach().numpy(), truth[:2], atol=1e-4)


def test_small_term_and_fixed_rows_are_not_restored():
    """A real term below the threshold stays pruned; rows with a user-fixed support are
    left alone."""
    theta, xdot, truth, inputs = _problem(small=-0.02)
    assert abs(truth[1]) < 0.05
    model = _model(theta, xdot, [True, False, False])
    weights = torch.ones_like(xdot)
    assert restore_terms(model, theta, xdot, weights, inputs, 0.05, torch.tensor([True])) == []
    theta, xdot, _, inputs = _problem()
    model = _model(theta, xdot, [True, False, False])
    assert restore_terms(model, theta, xdot, weights, inputs, 0.05, torch.tensor([False])) == []
    assert model.support.tolist() == [[True, False, False]]
