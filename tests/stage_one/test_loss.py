"""The loss of ``_stage_one/loss.py`` by its three paths on the same random inputs in
float64: torch's autograd (:func:`loss_terms`), the numpy step's loss written out
(:class:`NumpyLoss` on the samples) and the loss on the decoder's knots
(:class:`KnotLoss`). Terms, total loss and gradients (by the knots, the constants and
the KL divergence) agree to rtol 1e-10, the gradients' entries also to 1e-12 of the
largest by the knots (sums that cancel to zero); the wide library, whose misfit the knot path reads
through ``generators._knots``' float32 read-out matrix, to 1e-6."""

import numpy as np
import pytest
import torch
from torch import nn

from latentsindy._stage_one.coefficient_model import CoefficientModel
from latentsindy._stage_one.knot_loss import KnotLoss
from latentsindy._stage_one.loss import (
    TERMS,
    loss_terms,
    relative_spacing,
    roughness,
    term_weights,
    total_loss,
)
from latentsindy._stage_one.numpy_loss import NumpyLoss
from latentsindy.generators._knots import applies, knot_grid

RTOL, ATOL = 1e-10, 1e-12  # ATOL: relative to the largest gradient entry
PHASES = {1: (0.1, 0.3, 1.0, False), 2: (0.0, 2.0, 1.0, True)}  # training's weights
KL = 0.37


class _Given(nn.Module):
    """A generator that draws the given series (1, T, n F) and KL divergence."""

    def __init__(self, series, kl, spacing):
        super().__init__()
        self.series, self.kl, self.spacing = series, kl, spacing

    def sample(self, inputs, n_samples):
        return self.series, self.kl


def _problem(n_times, n_knots, n_traj, n_features, irregular, seed):
    """Random float64 data and knots (smooth, crossing zero, with kinks); two states,
    a pruned term, the sparsity on the first row only."""
    rng = np.random.default_rng(seed)
    n = 2
    theta = rng.standard_normal((n_traj, n_times, n_features))
    xdot = rng.standard_normal((n_traj, n_times, n))
    weights = rng.uniform(0.5, 1.5, (n_traj, n_times, n))
    grid = np.linspace(0, 6, n_knots)[:, None, None]
    knots = (np.sin(grid * rng.uniform(0.5, 3, (1, n, n_features)))
             + 0.1 * rng.standard_normal((n_knots, n, n_features)))
    support = np.ones((n, n_features))
    support[1, -1] = 0.0
    spacing = None
    if irregular:
        spacing = torch.tensor(np.diff(np.sort(rng.uniform(0, 10, n_times))))
    return theta, xdot, weights, knots, support, np.array([1.0, 0.0]), spacing


def _torch_path(problem, noise_var, threshold, phase):
    """Terms, loss and gradients by autograd, on the samples read from the knots."""
    theta, xdot, weights, knots, support, free, spacing = problem
    n_times = theta.shape[1]
    left, frac = knot_grid(n_times, knots.shape[0])
    leaf = torch.tensor(knots, requires_grad=True)
    f = torch.tensor(frac)[:, None, None]
    track = (1 - f) * leaf[left] + f * leaf[left + 1]  # (T, n, F)
    kl = torch.tensor(KL, dtype=torch.float64, requires_grad=True)
    gen = _Given(track.reshape(1, n_times, -1), kl, spacing)
    n, n_features = support.shape
    model = CoefficientModel(gen, torch.zeros(n, n_features, dtype=torch.float64),
                             torch.tensor(support, dtype=torch.bool),
                             torch.ones(n, n_features, dtype=torch.float64))
    as_t = torch.tensor
    terms = loss_terms(model, as_t(theta), as_t(xdot), as_t(weights), None, noise_var,
                       threshold, as_t(free))
    loss = total_loss(terms, *PHASES[phase])
    loss.backward()
    values = {k: float(v.detach()) if torch.is_tensor(v) else v for k, v in terms.items()}
    return (values, float(loss.detach()), leaf.grad.numpy(), model.constants.grad.numpy(),
            float(kl.grad), track.detach().numpy())


def _numpy_path(problem, noise_var, threshold, phase, samples, on_knots):
    """Terms, loss and gradients by :class:`NumpyLoss`: on the samples, or on the knots
    with ``on_knots``; the samples' gradient summed back onto the knots."""
    theta, xdot, weights, knots, support, free, spacing = problem
    if spacing is not None:
        spacing = relative_spacing(spacing).numpy()
    loss = NumpyLoss(theta, xdot, weights, noise_var, threshold, free, spacing,
                     KnotLoss(theta, xdot, weights, knots.shape[0]) if on_knots else None)
    xi = support * (knots if on_knots else samples)
    terms, grad_xi, grad_kl = loss(xi, support, KL, *PHASES[phase])
    grad_xi = grad_xi * support  # what reaches the model's series (a pruned term: none)
    by_constants = grad_xi.sum(axis=0)
    if not on_knots:  # d samples / d knots: the linear read-out's weights
        left, frac = knot_grid(theta.shape[1], knots.shape[0])
        flat = grad_xi.reshape(len(left), -1)
        by_knots = np.zeros((knots.shape[0], flat.shape[1]))
        np.add.at(by_knots, left, (1 - frac)[:, None] * flat)
        np.add.at(by_knots, left + 1, frac[:, None] * flat)
        grad_xi = by_knots.reshape(knots.shape)
    return terms, total_loss(terms, *PHASES[phase]), grad_xi, by_constants, grad_kl


def _agree(ours, ref, name, rtol=RTOL, atol=ATOL):
    """Every term, the loss and every gradient entry (``atol`` relative to the largest
    gradient entry by the knots)."""
    terms, loss, by_knots, by_constants, by_kl = ours
    assert list(terms) == list(ref[0]) == list(TERMS), name
    for key, value in ref[0].items():
        assert terms[key] == pytest.approx(value, rel=rtol, abs=1e-300), (name, key)
    assert loss == pytest.approx(ref[1], rel=rtol), name
    largest = np.abs(ref[2]).max()  # the constants' sums can cancel to rounding
    for got, expected in ((by_knots, ref[2]), (by_constants, ref[3])):
        np.testing.assert_allclose(got, expected, rtol=rtol, atol=atol * largest,
                                   err_msg=name)
    assert by_kl == pytest.approx(ref[4], rel=rtol), name


CASES = [  # n_times, n_knots, n_traj, n_features, irregular
    (700, 64, 1, 3, False), (2000, 256, 2, 3, False), (127, 64, 1, 3, False),
    (300, 256, 1, 3, False),  # under two samples per knot interval: no knot path
    (500, 32, 1, 3, True),  # irregular times: the roughness per unit time, no knot path
    (100, 32, 2, 8, False)]  # a wide library: the knot path's misfit on the samples


@pytest.mark.parametrize("n_times, n_knots, n_traj, n_features, irregular", CASES)
@pytest.mark.parametrize("phase", [1, 2])
@pytest.mark.parametrize("threshold", [0.05, 10.0])  # below and above the mean size
@pytest.mark.parametrize("fit", [True, False])  # False: no misfit, the penalties alone
def test_three_paths_agree(n_times, n_knots, n_traj, n_features, irregular, phase,
                           threshold, fit):
    problem = _problem(n_times, n_knots, n_traj, n_features, irregular, seed=n_times)
    if not fit:
        problem = (problem[0], problem[1], 0.0 * problem[2], *problem[3:])
    noise_var = 1e-4  # rough_bayes inside its range: the refit's scale shows
    *ref, samples = _torch_path(problem, noise_var, threshold, phase)
    assert 0.01 < ref[0]["rough_bayes"] < 1.0
    assert ref[0]["l1"] > 0 and ref[0]["rough"] > 0 and (ref[0]["mse"] > 0) == fit
    _agree(_numpy_path(problem, noise_var, threshold, phase, samples, False), ref,
           "numpy on the samples")
    if applies(n_times, n_knots, not irregular):
        float32_read_out = fit and n_knots * n_features > 2 * n_times  # a wide library
        tol = {"rtol": 1e-6, "atol": 1e-6} if float32_read_out else {}
        _agree(_numpy_path(problem, noise_var, threshold, phase, samples, True), ref,
               "numpy on the knots", **tol)


def test_the_comparison_sees_a_changed_term():
    """The agreement above is not vacuous: a share of the roughness off by a part in a
    million, or the sparsity's slope, shows well beyond the tolerance."""
    problem = _problem(700, 64, 1, 3, False, seed=0)
    *ref, samples = _torch_path(problem, 1e-4, 0.05, 1)
    ours = _numpy_path(problem, 1e-4, 0.05, 1, samples, True)
    _agree(ours, ref, "unchanged")
    changed = dict(ours[0], rough=ours[0]["rough"] * (1 + 1e-6))
    with pytest.raises(AssertionError):
        _agree((changed, *ours[1:]), ref, "changed")
    with pytest.raises(AssertionError):
        _agree((*ours[:2], ours[2] * (1 + 1e-9), *ours[3:]), ref, "changed")


def test_term_weights_are_the_total_loss():
    """:func:`total_loss` is the terms weighted by :func:`term_weights`: the refit has
    no sparsity and scales the roughness by ``rough_bayes``."""
    terms = {"mse": 1.5, "kl": 0.25, "l1": 3.0, "rough": 0.5, "rough_bayes": 0.2}
    for l1_weight, rough_weight, kl_weight, refit in PHASES.values():
        weights = term_weights(l1_weight, rough_weight, kl_weight, refit, 0.2)
        expected = sum(weights[k] * terms[k] for k in ("mse", "kl", "l1", "rough"))
        assert total_loss(terms, l1_weight, rough_weight, kl_weight, refit) == pytest.approx(
            expected, rel=1e-15)
    assert term_weights(0.1, 2.0, 1.0, True, 0.2) == {"mse": 1.0, "kl": 1.0, "l1": 0.0,
                                                      "rough": 0.4}


def test_roughness_shares():
    """The roughness of a straight line is its total variation's share alone; a kink
    adds the second differences' share."""
    line = torch.linspace(0.0, 1.0, 11, dtype=torch.float64)[None, :, None]
    assert float(roughness(line)[0]) == pytest.approx(0.5 * 0.1, rel=1e-12)
    kink = torch.cat([line[:, :6], line[:, 5:6] - (line[:, 6:] - line[:, 5:6])], dim=1)
    second = 2 * 0.1 / 9  # one second difference of 0.2, among nine
    assert float(roughness(kink)[0]) == pytest.approx(0.5 * second + 0.5 * 0.1, rel=1e-12)
