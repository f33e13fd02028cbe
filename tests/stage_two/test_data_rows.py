"""The refinement's data rows, compiled (``data_rows``), against the array operations
they replace, in numpy and in torch: equal to the bit, white or AR(1) noise, padded
samples and held-out weights included."""

import numpy as np
import pytest
import torch

from latentsindy._stage_two.fit.data_rows import data_rows
from latentsindy._stage_two.fit.whiten import scale, whiten


def _group(rng, whitened, n_seg=20, n_samples=30, n_obs=2, n_states=3, n_free=4):
    vals = rng.normal(size=(n_seg, n_samples, n_obs))
    sens = rng.normal(size=(n_seg, n_samples, n_obs, n_states + n_free))
    observed = rng.normal(size=(n_seg, n_samples, n_obs))
    mask = np.ones((n_seg, n_samples), bool)
    mask[-1, 20:] = False  # the last segment's padding
    weights = (rng.random(n_seg) > 0.3).astype(float)[:, None] * mask  # held out: 0
    sigma = rng.uniform(0.1, 2.0, n_obs)
    carry = None
    if whitened:
        carry = np.where(mask[..., None], rng.uniform(0.0, 0.95, (n_seg, n_samples, n_obs)),
                         0.0)
        carry[:, 0] = 0.0  # a segment's first sample
    return vals, sens, observed, mask, sigma, weights, carry, n_states


def _arrays(xp, vals, sens, observed, mask, sigma, weights, carry, n_states):
    """The rows as array operations (the refinement's before they were compiled)."""
    as_ = (lambda a: a) if xp is np else (lambda a: None if a is None else torch.as_tensor(a))
    vals, sens, observed, mask, sigma, weights, carry = map(
        as_, (vals, sens, observed, mask, sigma, weights, carry))
    w = weights[..., None]
    resid = whiten((vals - observed) / sigma * mask[..., None], carry) * w
    s = whiten(sens / sigma[:, None] * mask[..., None, None], carry) * w[..., None]
    jac = xp.concatenate([s[..., n_states:], s[..., :n_states]], -1) if xp is np else \
        torch.cat([s[..., n_states:], s[..., :n_states]], -1)
    out = resid, jac.reshape(len(vals), -1, jac.shape[-1])
    return [np.asarray(a) for a in out]


@pytest.mark.parametrize("whitened", [False, True])
@pytest.mark.parametrize("xp", [np, torch], ids=["numpy", "torch"])
def test_the_rows_are_the_array_operations_to_the_bit(whitened, xp):
    rng = np.random.default_rng(3)
    group = _group(rng, whitened)
    resid, jac = data_rows(*group)
    want_resid, want_jac = _arrays(xp, *group)
    assert resid.shape == want_resid.shape and jac.shape == want_jac.shape
    assert np.array_equal(resid, want_resid) and np.array_equal(jac, want_jac)
    # the padding gives zero rows, and so do the held-out segments
    assert not resid[-1, 20:].any() and not jac[-1, 40:].any()
    held_out = group[5][:, 0] == 0
    assert held_out.any() and not resid[held_out].any() and not jac[held_out].any()



def test_whitening_takes_out_the_previous_samples_share():
    """AR(1) residuals ``e_i = a e_(i-1) + sqrt(1 - a^2) u_i`` whiten back to ``u``."""
    a, n = 0.8, 6
    u = np.random.default_rng(0).normal(size=n)
    e = np.empty(n)
    e[0] = u[0]
    for i in range(1, n):
        e[i] = a * e[i - 1] + np.sqrt(1 - a * a) * u[i]
    carry = np.full((1, n, 1), a)
    carry[0, 0] = 0.0
    resid, _ = data_rows(e[None, :, None], np.zeros((1, n, 1, 1)), np.zeros((1, n, 1)),
                         np.ones((1, n), bool), np.ones(1), np.ones((1, n)), carry, 1)
    np.testing.assert_allclose(resid[0, :, 0], u, rtol=1e-12, atol=1e-15)


def test_the_whitening_takes_torchs_square_roots():
    """``scale`` is torch's ``sqrt(1 - a^2)``, which the held-out scores also take; where
    torch's vectorised square root is not the correctly rounded one (MKL builds: 1-2%
    of float64 values), numpy's would give other misfits in the last bits."""
    a = np.random.default_rng(0).uniform(0.0, 0.99, (50, 40, 2))
    want = torch.sqrt(1.0 - torch.as_tensor(a) ** 2).numpy()
    assert np.array_equal(scale(a), want)
    if np.array_equal(want, np.sqrt(1.0 - a**2)):
        pytest.skip("torch's square root is correctly rounded on this platform")
