"""The dynamic SINDy training loss of timeVAE: its one definition.

On normalised data, with ``xi`` the coefficient series (S, T, n, F) drawn by the model,
``a`` its support (1 kept, 0 pruned) and ``N_a = max(sum a, 1)``::

    loss = mse + kl_weight kl + l1_weight l1 + rough_weight [rough_bayes] rough

* ``mse = mean_{s,b,t,i} w (theta . xi - xdot)^2``: the derivative misfit, each sample
  weighted by its inverse relative noise variance ``w``;
* ``kl = 2 s2 KL / N``: the generator's KL divergence in the misfit's units (the ELBO
  ``sum r^2 / (2 s2) + KL`` times ``2 s2 / N``; ``s2`` the derivative noise variance,
  ``N`` the misfit's count);
* ``l1 = sum_ij free_i c log(1 + size_ij / c)``: a reweighted L1 (log) penalty on
  ``size_ij = a_ij mean_t |xi_tij|`` with ``c`` the pruning threshold (slope 1 at zero,
  ``1 / (1 + size / c)`` beyond: small terms are pushed hard, the terms that stay are
  barely shrunk); only on the rows that are ``free`` (not fixed by the user);
* ``rough = sum_ij a_ij R_ij / (N_a max(mean_abs, c))``: the roughness :func:`roughness`
  (``BEND_SHARE`` of the mean absolute second difference, ``TV_SHARE`` of the mean
  absolute first difference) relative to the coefficients' mean size ``mean_abs =
  sum size / N_a`` (held fixed: not differentiated), never to less than ``c``;
* ``rough_bayes = clip(s2 T N_a / n, 0.01, 1)`` scales the roughness in the refit (a
  Laplace prior on slope changes in ELBO units); the refit has no ``l1`` term.

Three paths evaluate it: :func:`loss_terms` (torch, autograd: the GPU's), the numpy
step (``numpy_loss``: the same terms and their gradient written out, the CPU's) and
the loss on the decoder's knots (``knot_loss``: an exact re-expression of the misfit,
magnitude and roughness on the knots). The weights, shares, the assembly of the terms
(:func:`penalties`, :func:`kl_in_mse_units`, :func:`rough_bayes`) and their combination
(:func:`term_weights`, :func:`total_loss`) are this module's, for all three; the
assembly runs on torch tensors and on numpy arrays alike, in the same order of
operations. Tests hold the three paths to each other in float64.
"""

from __future__ import annotations

import numpy as np
import torch

BEND_SHARE = 0.5  # share of the mean absolute second difference in the roughness
TV_SHARE = 0.5  # share of the mean absolute first difference (total variation)
MIN_STEP = 1e-3  # smallest time step, relative to the mean (see relative_spacing)
ROUGH_BAYES_RANGE = (0.01, 1.0)  # bounds of the refit's roughness scale
TERMS = ("mse", "kl", "l1", "rough", "rough_bayes")  # the terms, in the record's order


def _value(x):
    """A torch tensor as is (autograd follows it), anything else as a Python float."""
    return x if torch.is_tensor(x) else float(x)


def _at_least(x, low):
    return x.clamp_min(low) if torch.is_tensor(x) else max(x, low)


def _fixed(x):
    """``x`` held fixed: not differentiated."""
    return x.detach() if torch.is_tensor(x) else x


def kl_in_mse_units(kl, noise_var, count):
    """The KL divergence in the misfit's units: ``2 noise_var kl / count``."""
    return 2.0 * noise_var * kl / count


def rough_bayes(noise_var, n_times, n_active, n_states) -> float:
    """The refit's roughness scale ``clip(noise_var n_times n_active / n_states)``."""
    low, high = ROUGH_BAYES_RANGE
    return min(high, max(low, float(noise_var * n_times * _fixed(n_active) / n_states)))


def penalties(size, rough, active, free, threshold, noise_var, n_times, n_states):
    """The sparsity and roughness terms from per-term statistics.

    Parameters
    ----------
    size, rough : (n, F) tensors or arrays
        ``mean_t |xi|`` masked by ``active``, and :func:`roughness` (unmasked).
    active : (n, F)
        The support, as numbers.
    free : (n,)
        1 on the rows the sparsity acts on, else 0.
    threshold, noise_var : float
    n_times, n_states : int
        Samples per trajectory, equations.

    Returns
    -------
    terms : dict
        ``l1``, ``rough`` (tensors with tensors, else floats) and ``rough_bayes``.
    n_active, mean_abs
        The normalisation's parts, for a gradient written out.
    """
    n_active = _at_least(_value(active.sum()), 1.0)
    rough = _value((rough * active).sum()) / n_active
    mean_abs = _value(size.sum()) / n_active
    rough = rough / _at_least(_fixed(mean_abs), threshold)
    scale = rough_bayes(noise_var, n_times, n_active, n_states)
    log1p = torch.log1p if torch.is_tensor(size) else np.log1p
    l1 = _value((threshold * log1p(size / threshold) * free[:, None]).sum())
    return {"l1": l1, "rough": rough, "rough_bayes": scale}, n_active, mean_abs


def roughness_scale(n_active, mean_abs, threshold) -> float:
    """The derivative of :func:`penalties`' ``rough`` by ``sum a R``."""
    return 1.0 / (n_active * max(mean_abs, threshold))


def sparsity_gradient(size, threshold, free, weight):
    """The derivative of ``weight l1`` (:func:`penalties`) by ``size``."""
    return weight * free[:, None] / (1.0 + size / threshold)


def term_weights(l1_weight, rough_weight, kl_weight, rough_scaled, bayes) -> dict:
    """Each term's weight in the loss: the roughness scaled by ``bayes`` (the term
    ``rough_bayes``) only if ``rough_scaled`` (the refit), which has no ``l1`` term."""
    scale = bayes if rough_scaled else 1.0
    return {"mse": 1.0, "kl": kl_weight, "l1": 0.0 if rough_scaled else l1_weight,
            "rough": rough_weight * scale}


def total_loss(terms, l1_weight, rough_weight, kl_weight, rough_scaled):
    """The training loss from the terms (tensors or floats), weighted by
    :func:`term_weights`."""
    weights = term_weights(l1_weight, rough_weight, kl_weight, rough_scaled,
                           terms["rough_bayes"])
    reg = weights["rough"] * terms["rough"]
    if not rough_scaled:
        reg = weights["l1"] * terms["l1"] + reg
    return terms["mse"] + weights["kl"] * terms["kl"] + reg


def relative_spacing(spacing: torch.Tensor) -> torch.Tensor:
    """Time steps in units of their mean, at least ``MIN_STEP``: two samples nearly at
    the same time share one position in float32 (a zero step, 0/0 slopes otherwise)."""
    return (spacing / spacing.mean()).clamp_min(MIN_STEP)


def roughness(track: torch.Tensor, spacing: torch.Tensor | None = None) -> torch.Tensor:
    """Smoothness penalty of both generators, per trailing entry: ``BEND_SHARE`` of the
    mean absolute second difference along time (dim 1) plus ``TV_SHARE`` of the mean
    absolute first difference (total variation).

    Total variation alone penalises amplitude: it flattens peaks and troughs (on
    prey-only LV at 1% noise the hidden state sat 0.059 above the true minima). Slope
    changes do not: clipping a peak does not lower them. A pure slope-change penalty,
    though, lets constant coefficients drift linearly (a constant oscillator's
    coefficient drifted by 8.7%, and the switch and Lorenz bars failed), so half of the
    total variation stays: minima now within 0.033, the other bars unchanged. A jump
    costs 1.5 times what total variation alone charged; sample-to-sample noise is
    penalised as before.

    ``spacing`` (len - 1,) are the times between consecutive points of the track (None:
    equal). Then the second differences are divided differences in units of the mean
    spacing (:func:`relative_spacing`), each weighted by the time it stands for: a
    prior per unit time, not per sample (equal spacing gives the plain differences).
    Total variation needs no change: it is the same whatever the sampling.
    """
    if track.shape[1] < 3:
        return track.new_zeros(track.shape[2:])
    first = track[:, 1:] - track[:, :-1]
    if spacing is None:
        second = (track[:, 2:] - 2 * track[:, 1:-1] + track[:, :-2]).abs()
    else:
        h = relative_spacing(spacing).to(track.dtype)
        h = h.reshape(1, -1, *([1] * (track.dim() - 2)))
        slope = first / h
        width = h[:, 1:] + h[:, :-1]
        second = (2 * (slope[:, 1:] - slope[:, :-1]) / width).abs() * (width / 2)
    return BEND_SHARE * second.mean(dim=(0, 1)) + TV_SHARE * first.abs().mean(dim=(0, 1))


def loss_terms(model, theta, xdot, weights, inputs, noise_var, threshold, free_rows):
    """The loss's terms (:data:`TERMS`) on normalised data, by torch (autograd).

    ``weights`` (n_traj, n_times, n_states) are per-sample likelihood weights (inverse
    relative noise variance of the derivative); ``noise_var`` the noise variance;
    ``free_rows`` (n_states,) the rows the sparsity acts on, as numbers.
    """
    xi, kl = model(inputs, 1)
    pred = torch.einsum("btf,stnf->sbtn", theta, xi)
    mse = torch.mean(weights[None] * (pred - xdot[None]) ** 2)
    kl = kl_in_mse_units(kl, noise_var, xdot.numel())
    active = model.support.to(xi.dtype)
    size = xi.abs().mean(dim=(0, 1)) * active  # mean |Xi| over time, per term
    rough = roughness(xi, model.generator.spacing)
    terms, _, _ = penalties(size, rough, active, free_rows, threshold, noise_var,
                            xi.shape[1], xdot.shape[-1])
    return {"mse": mse, "kl": kl, **terms}
