"""On a CUDA device: stage one (both generators), the refinement's integrations and the
whole discovery give what they give on the CPU. Skipped where torch sees no GPU (CI)."""

import numpy as np
import pysindy as ps
import pytest
import sympy as sp
import torch
from conftest import check_lorenz, r2

from latentsindy import DynamicSINDy, discover_hidden, load, systems
from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.fit.refine import Problem, RefineOptions

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")


def test_timevae_on_the_gpu_finds_the_switch(tmp_path):
    """The oscillator with a switching A(t) at 1% noise (stage one's accuracy test):
    the same support on the GPU as on the CPU, R^2 of A(t) >= 0.95 on both; a model
    fitted on the GPU saves and loads (on the CPU) with the same mean coefficients, to
    the GPU's precision (cuDNN runs the decoder's convolutions in TF32 by default: 10
    mantissa bits, measured 5e-4 relative on an H200)."""
    data = systems.harmonic_oscillator(A=systems.Switch(-1.0, -4.0, at=12.0), B=1.0,
                                       t_end=25.0, n_times=1000, noise=0.01, seed=1)
    found = {}
    for device in ("cpu", "cuda"):
        model = DynamicSINDy(ps.PolynomialLibrary(degree=2), device=device, verbose=False)
        coefs = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(16)
        found[device] = (coefs.active_terms(), r2(coefs.term("x", "y"), data.parameters["A"]))
    assert found["cuda"][0] == found["cpu"][0] == [("x", "y"), ("y", "x")]
    assert min(found["cuda"][1], found["cpu"][1]) >= 0.95
    model.save(tmp_path / "gpu.npz")
    np.testing.assert_allclose(load(tmp_path / "gpu.npz").coefficients(2).mean,
                               model.coefficients(2).mean, rtol=2e-3, atol=2e-3)


def test_hypersindy_on_the_gpu_keeps_lorenz():
    """Lorenz with a sigmoid sigma(t), 1% noise, T=4000, dynamic HyperSINDy on the GPU:
    exact support, sigma(t) R^2 >= 0.9, constants within 5% (the CPU test's bars)."""
    sigma = systems.Sigmoid(8.0, 14.0, at=20.0, sharpness=0.5)
    data = systems.lorenz(sigma=sigma, n_times=4000, t_end=40.0, noise=0.01)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), generator="hypersindy",
                         device="cuda", verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y", "z"]).coefficients(8)
    check_lorenz(coefs, data)


def test_refinement_integrates_on_the_gpu_as_on_the_cpu():
    """One multiple-shooting pass (float64) on either device: the same states and
    sensitivities to 1e-9, hence the same fit."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=1500, t_end=15.0, noise=0.01)
    x, h = sp.symbols("x h", real=True)
    coef = np.array([[1.0, 0.0, 0.0, 0.0], [0.075, 1.5, -1.5, -0.075]]) * [[1.0], [1.2]]
    system = ParametricSystem(("x", "h"), 1, (x * h, sp.Integer(1), h, x), coef,
                              np.array([[False] * 4, [True] * 4]))
    guess = [np.column_stack([data.x_clean[:, 0], 1.0 - 0.1 * data.x_clean[:, 1]])]
    fits = [Problem(system, [data.t], [data.x[:, :1]], guess, RefineOptions(device=d)).fit()
            for d in ("cpu", "cuda")]
    np.testing.assert_allclose(fits[1].system.coef, fits[0].system.coef, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(fits[1].starts, fits[0].starts, rtol=1e-9, atol=1e-12)


def test_discovery_on_the_gpu_gives_the_cpu_law():
    """Prey-only Lotka-Volterra (1% noise): the same structure on both devices, every
    coefficient within 2% of the CPU's and of the truth."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=1000, noise=0.01, seed=1)
    lib = ps.PolynomialLibrary(degree=3, include_bias=False)
    runs = [discover_hidden(data.x[:, :1], lib, t=data.t, feature_names=["x"], device=d,
                            verbose=False) for d in ("cpu", "cuda")]
    assert all(r.confident and r.hidden_names == ("h0",) for r in runs)
    assert [(a.state, a.feature) for a in runs[1].terms] == \
        [(a.state, a.feature) for a in runs[0].terms]
    np.testing.assert_allclose([a.value for a in runs[1].terms],
                               [a.value for a in runs[0].terms], rtol=0.02)
