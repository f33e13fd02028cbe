"""Dynamic HyperSINDy: the sequential generator, its windowed training and its bars."""

import numpy as np
import pysindy as ps
import pytest
import torch
from conftest import check_lorenz, r2

from latentsindy import DynamicSINDy, systems
from latentsindy.generators import HyperSINDy, HyperSINDyOptions
from latentsindy.generators.hypersindy import detach_state, interpolate_chunks
from latentsindy.options import SequentialTrainingOptions, TrainingOptions


def _trained_like(gen):
    """Non-zero output layer and basis tensors, as after training."""
    torch.nn.init.normal_(gen.decoder[-1].base.weight)
    torch.nn.init.normal_(gen.to_alpha.weight)
    for layer in gen.decoder:
        torch.nn.init.normal_(layer.bases, std=0.3 / layer.bases.shape[1] ** 0.5)
    return gen


def test_shapes_and_parameters_independent_of_length():
    gen = HyperSINDy(4, 6, HyperSINDyOptions())
    n_params = sum(p.numel() for p in gen.parameters())
    for n_times in (37, 1000, 5003):
        series, kl = gen.sample(torch.randn(2, 4, n_times), n_samples=3)
        assert series.shape == (3, n_times, 6)
        assert kl.ndim == 0 and float(kl.detach()) >= 0
    assert n_params == sum(p.numel() for p in HyperSINDy(4, 6, HyperSINDyOptions()).parameters())


def test_reading_in_windows_carries_the_hypernetwork_state():
    """Reading window by window with the state carried and detached (truncated
    backpropagation) gives the same coefficients as the generator's own read, and the
    carried state matters: a fresh state per window gives different coefficients."""
    torch.manual_seed(0)
    gen = _trained_like(HyperSINDy(4, 6, HyperSINDyOptions()))
    gen.allocate(2000)
    torch.nn.init.normal_(gen.codes.weight)
    inputs = torch.randn(1, 4, 2000)
    with torch.no_grad():
        whole, _ = gen.sample(inputs, 0, window=500)
        state, carried, fresh = None, [], []
        for start in range(0, 2000, 500):
            piece = inputs[..., start:start + 500]
            out, _, state = gen.window(piece, 0, state, start)
            state = detach_state(state)
            carried.append(out)
            fresh.append(gen.window(piece, 0, None, start)[0])
    chunks = torch.cat(carried, dim=1)
    assert torch.allclose(whole, interpolate_chunks(chunks, 2000, 10), atol=1e-5)
    assert not torch.allclose(torch.cat(fresh, dim=1), chunks, atol=1e-4)


def test_chunk_offsets_select_the_window_rows():
    gen = HyperSINDy(4, 6, HyperSINDyOptions())
    like = torch.zeros(1)
    assert torch.equal(gen.chunk_offsets(0, 95, like), torch.zeros(10, 25))  # none allocated
    gen.allocate(95)  # 10 chunks of 10 steps (the last one short)
    with torch.no_grad():
        gen.codes.weight.copy_(torch.arange(10.0)[:, None].expand(10, 25))
        rows = gen.chunk_offsets(50, 100, like)[:, 0]  # chunks 5..14; 10.. lie past the end
    assert torch.equal(rows, torch.tensor([5.0, 6, 7, 8, 9, 0, 0, 0, 0, 0]))


def test_lstm_makes_coefficients_depend_on_the_past():
    torch.manual_seed(0)
    gen = _trained_like(HyperSINDy(4, 6, HyperSINDyOptions()))
    a = torch.randn(1, 4, 400)
    b = a.clone()
    b[..., :200] = torch.randn(1, 4, 200)  # same recent data, different past
    with torch.no_grad():
        out_a, _ = gen.sample(a, 0, window=200)
        out_b, _ = gen.sample(b, 0, window=200)
    assert (out_a[0, 210:] - out_b[0, 210:]).abs().max() > 1e-3
    mlp = HyperSINDy(4, 6, HyperSINDyOptions(hypernetwork="mlp"))
    alpha, state = mlp.mixing(torch.randn(1, 7, 25), None)
    assert alpha.shape == (1, 7, 10) and state is None  # an MLP carries no state


def test_chunk_interpolation_is_exact_for_linear_series():
    n_times, chunk = 95, 10
    steps = torch.arange(n_times, dtype=torch.float64)
    starts = torch.arange(0, n_times, chunk, dtype=torch.float64)
    centres = (starts + torch.clamp(starts + chunk, max=n_times) - 1) / 2
    values = (2.0 * centres - 3.0)[None, :, None]
    out = interpolate_chunks(values, n_times, chunk)[0, :, 0]
    inside = (steps >= centres[0]) & (steps <= centres[-1])
    assert torch.allclose(out[inside], 2.0 * steps[inside] - 3.0)


def test_options_are_validated():
    data = systems.harmonic_oscillator(n_times=200)
    with pytest.raises(TypeError, match="Unknown option"):
        DynamicSINDy(generator="hypersindy", generator_options={"latnet_dim": 3},
                     verbose=False).fit(data.x, data.t)
    with pytest.raises(ValueError, match="hypernetwork must be one of"):
        HyperSINDyOptions(hypernetwork="gru")
    with pytest.raises(ValueError, match="mode must be one of"):
        SequentialTrainingOptions(mode="offline")
    with pytest.raises(ValueError, match="window must be >= 1"):
        SequentialTrainingOptions(window=0)
    with pytest.raises(TypeError, match="must be a SequentialTrainingOptions"):
        DynamicSINDy(generator="hypersindy", training=TrainingOptions(),
                     verbose=False).fit(data.x, data.t)
    with pytest.raises(TypeError, match="Unknown training option.*online_steps"):
        DynamicSINDy(generator="timevae", training={"online_steps": 3},
                     verbose=False).fit(data.x, data.t)


def test_alternate_mode_trains_one_part_at_a_time():
    data = systems.harmonic_oscillator(n_times=400)
    opts = {"mode": "alternate", "support_steps": 1, "refit_steps": 0, "min_epochs": 2,
            "window": 400}  # one window: one step per epoch
    model = DynamicSINDy(generator="hypersindy", training=opts, verbose=False, seed=3)
    model.fit(data.x, data.t)
    fresh = DynamicSINDy(generator="hypersindy", training={**opts, "support_steps": 0},
                         verbose=False, seed=3)
    fresh.fit(data.x, data.t)  # same seed, no steps: the initial state
    # the hypernetwork first (main module fixed), then the main module
    assert [h["trained"] for h in model.history_] == [("hyper",), ("main", "codes")]
    gen, gen0 = model.model_.generator, fresh.model_.generator
    assert not torch.equal(gen.lstm.weight_ih_l0, gen0.lstm.weight_ih_l0)
    assert not torch.equal(gen.encoder[0].weight, gen0.encoder[0].weight)
    joint = DynamicSINDy(generator="hypersindy", training={**opts, "mode": "joint"},
                         verbose=False, seed=3).fit(data.x, data.t)
    assert [h["trained"] for h in joint.history_] == [("main", "hyper", "codes")] * 2


def test_online_mode_records_the_track_window_by_window():
    data = systems.harmonic_oscillator(A=systems.Switch(-1.0, -3.0, at=5.0), n_times=600)
    opts = {"mode": "online", "support_steps": 20, "refit_steps": 1, "window": 200,
            "online_steps": 3}
    model = DynamicSINDy(ps.PolynomialLibrary(degree=1, include_bias=False),
                         generator="hypersindy", training=opts, verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(n_samples=4)
    assert coefs.mean.shape == (600, 2, 2)
    assert model.model_.track_mean.shape[0] == 60  # one record per chunk of 10 steps
    assert sum(h["phase"] == 2 for h in model.history_) == 3 * 3  # 3 windows x 3 steps


@pytest.mark.slow  # 80-105 s: run with --runslow
def test_oscillator_sigmoid_A_at_one_percent_noise():
    """Issue 4 bar: R^2 of A(t) >= 0.95 with generator="hypersindy" (default settings).

    Measured: R^2 0.9997, B within 0.01% (a constant: its variation is frozen), support
    exact.
    """
    data = systems.harmonic_oscillator(A=systems.Sigmoid(-1.0, -4.0, at=12.0, sharpness=1.0),
                                       B=1.0, t_end=25.0, n_times=1000, noise=0.01, seed=1)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), generator="hypersindy", verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(n_samples=16)
    assert coefs.active_terms() == [("x", "y"), ("y", "x")]
    assert r2(coefs.term("x", "y"), data.parameters["A"]) >= 0.95
    assert np.max(np.abs(coefs.term("y", "x") - 1.0)) < 0.05


@pytest.mark.slow  # 80-105 s: run with --runslow
def test_lorenz_sigmoid_sigma_over_ten_thousand_samples():
    """Issue 4 bar: Lorenz with a sigmoid sigma(t), 1% noise, T = 10,000: R^2 of sigma(t)
    >= 0.9 in both terms, the other coefficients within 5%, no spurious terms; the
    constant equations are fitted as constants (their variation is frozen).

    Measured (data/model seeds 0, 1, 2): R^2 0.997, 0.996, 0.996; constants within
    0.3%, 2.3%, 1.8%.
    """
    n = 10_000
    sigma = systems.Sigmoid(8.0, 14.0, at=n / 200, sharpness=0.5)
    data = systems.lorenz(sigma=sigma, n_times=n, t_end=n / 100, noise=0.01)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), generator="hypersindy", verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y", "z"]).coefficients(8)
    check_lorenz(coefs, data)
    assert model.time_varying_[1:].sum() == 0  # ydot and zdot have constant coefficients


@pytest.mark.slow  # 80-105 s: run with --runslow
def test_discover_hidden_with_hypersindy_on_lotka_volterra():
    """Issue 4 bar: the LV tutorial's accuracy with generator="hypersindy" (noise-free:
    hidden R^2 >= 0.999, hidden-equation coefficients within 1%; stage two now refines
    by integration, measured 0.99999 and 0.01%)."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    result = _prey_only_with_hypersindy(data)
    assert result.compare_hidden(data.x_clean[:, 1]).r2[0] >= 0.999
    errors, extra, missing = _hidden_law_errors(result)
    assert extra == [] and missing == []
    assert max(errors.values()) <= 0.01


def _prey_only_with_hypersindy(data, **options):
    """``discover_hidden`` on the prey of ``data`` (the LV tutorial's call), HyperSINDy."""
    from latentsindy import discover_hidden

    return discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3, include_bias=False),
                           t=data.t, feature_names=["x"], hidden_names=["h"],
                           generator="hypersindy", verbose=False, **options)


def _hidden_law_errors(result):
    """Relative error of each term of the tutorial's hidden law, extra and missing terms."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples"))
    import lotka_volterra

    return lotka_volterra.equation_errors(result.equation("h"), lotka_volterra.TRUE_HIDDEN)


def test_discover_hidden_with_hypersindy_on_small_settings(monkeypatch):
    """The whole discovery with generator="hypersindy", trained for 20 + 20 steps (the
    pipeline in seconds; its accuracy at default settings is the slow test above):
    stage one's exact model still finds the law, and stage two closes it (measured:
    hidden-equation coefficients within 0.3%, hidden R^2 1.0000)."""
    calls, window = [], HyperSINDy.window
    monkeypatch.setattr(HyperSINDy, "window",
                        lambda self, *a, **k: calls.append(1) or window(self, *a, **k))
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=600, t_end=30.0, noise=0.01)
    small = {"support_steps": 20, "refit_steps": 20, "min_epochs": 1, "window": 200}
    result = _prey_only_with_hypersindy(data, training=small, seed=0)
    assert calls and result.state_names == ("x", "h")  # trained by HyperSINDy
    assert result.compare_hidden(data.x_clean[:, 1]).r2[0] >= 0.99
    errors, extra, missing = _hidden_law_errors(result)
    assert extra == [] and missing == []
    assert max(errors.values()) <= 0.02
