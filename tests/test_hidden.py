"""Stage two: discover_hidden on Lotka-Volterra and the oscillator, and the round trips."""

import sys
from pathlib import Path

import numpy as np
import pysindy as ps
import pytest
import sympy as sp
import torch

from latentsindy import HiddenDiscovery, discover_hidden, load, systems

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
import lotka_volterra  # noqa: E402
import oscillator  # noqa: E402


@pytest.fixture(scope="module")
def lv():
    """Noise-free prey-only Lotka-Volterra at T=2000, default settings."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3, include_bias=False),
                             t=data.t, feature_names=["x"], hidden_names=["h"], verbose=False)
    return data, result


def test_lv_hidden_state_and_equation(lv):
    data, result = lv
    assert isinstance(result, HiddenDiscovery)
    assert result.state_names == ("x", "h")
    assert result.hidden_terms == (("x", "x"),)
    assert result.compare_hidden(data.x_clean[:, 1]).r2[0] >= 0.999
    errors, extra, missing = lotka_volterra.hidden_equation_errors(result)
    assert extra == [] and missing == []
    assert max(errors.values()) <= 0.01
    x, h = sp.symbols("x h", real=True)
    assert result.rhs["x"] == x * h


def test_lv_with_one_percent_noise():
    """Issue 3 bar at 1% noise: hidden R^2 >= 0.99, hidden-equation coefficients within
    3%, no extra or missing terms (measured 0.99886 and 1.9%)."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000, noise=0.01)
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3, include_bias=False),
                             t=data.t, feature_names=["x"], hidden_names=["h"], verbose=False)
    assert result.compare_hidden(data.x_clean[:, 1]).r2[0] >= 0.99
    errors, extra, missing = lotka_volterra.hidden_equation_errors(result)
    assert extra == [] and missing == []
    assert max(errors.values()) <= 0.03


def test_closure_integral_refit_is_exact_on_clean_data():
    """The closure's final fit (increments over ``span`` samples against the library's
    integrals) is exact on exact data: the predator's equation of noise-free
    Lotka-Volterra within 1e-4, pointwise-like (span 1) or over 45 samples."""
    from latentsindy._closure import fit_closure

    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    y, x = data.x_clean[:, 1:2], data.x_clean[:, :1]
    ydot = data.x_dot[:, 1:2]
    for span in (1, 45):
        model, _ = fit_closure([y], [ydot], [x], [data.t], ps.PolynomialLibrary(degree=2),
                               ["y"], ["x"], span=span)
        found = dict(zip(model.get_feature_names(), model.coefficients()[0], strict=True))
        assert {k for k, v in found.items() if v != 0} == {"y", "y x"}
        assert found["y"] == pytest.approx(-1.5, rel=1e-4)
        assert found["y x"] == pytest.approx(0.075, rel=1e-4)


def test_lv_affine_map_recovers_predator(lv):
    data, result = lv
    cmp = result.compare_hidden(data.x_clean[:, 1])
    # y = (alpha - h) / beta  ->  scale -1/beta = -10, offset alpha/beta = 10
    assert cmp.scale[0, 0] == pytest.approx(-10.0, rel=0.01)
    assert cmp.offset[0] == pytest.approx(10.0, rel=0.01)


def test_sympy_rhs_matches_pysindy_prediction(lv):
    _, result = lv
    field = result.vector_field()
    states = result.states
    ours = field(0.0, states)[:, 1]
    theirs = result.sindy.predict(result.hidden, u=result.all_observed[0])[:, 0]
    # pysindy's library sees the smoothed observed states; on noise-free data they agree
    np.testing.assert_allclose(ours, theirs, rtol=1e-3, atol=1e-6 * np.abs(theirs).max())


def test_vector_field_numpy_and_torch_agree(lv):
    _, result = lv
    field = result.vector_field()
    y = result.states[::100]
    np.testing.assert_allclose(field(0.0, torch.as_tensor(y)).numpy(), field(0.0, y), rtol=1e-12)


def test_simulation_reproduces_observed(lv):
    data, result = lv
    sim = result.simulate()
    assert sim.success, sim.message
    nrmse = np.sqrt(np.mean((sim.x[:, 0] - data.x[:, 0]) ** 2)) / np.std(data.x[:, 0])
    assert nrmse < 0.1


def test_blow_up_is_reported_not_hung(lv):
    _, result = lv
    sim = result.simulate(t=np.linspace(0, 50, 100), x0=[1e4, 50.0])
    assert sim.status in {"blow_up", "step_budget"}
    assert "x0" in sim.message or "max_steps" in sim.message
    assert np.all(np.isnan(sim.x))


def test_save_load_round_trip(lv, tmp_path):
    _, result = lv
    path = tmp_path / "lv.npz"
    result.save(path)
    back = load(path)
    assert back.state_names == result.state_names
    assert back.hidden_terms == result.hidden_terms
    for name in result.state_names:
        assert sp.simplify(back.rhs[name] - result.rhs[name]) == 0
    np.testing.assert_array_equal(back.hidden, result.hidden)
    np.testing.assert_array_equal(back.coefficients.mean, result.coefficients.mean)
    assert back.to_latex() == result.to_latex()


def test_load_rejects_other_files(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, meta=np.array('{"format": "something"}'))
    with pytest.raises(ValueError, match="not a saved HiddenDiscovery"):
        load(path)


def test_summary_and_latex(lv):
    _, result = lv
    assert "h = coefficient of x in dx/dt" in result.summary()
    assert r"\dot{x} &= h x" in result.to_latex()
    assert len(result.equations) == 2


def test_compare_hidden_length_mismatch(lv):
    _, result = lv
    with pytest.raises(ValueError, match="true_hidden has 10 rows"):
        result.compare_hidden(np.zeros(10))


def test_simulate_bad_x0(lv):
    _, result = lv
    with pytest.raises(ValueError, match=r"x0 must have shape \(2,\)"):
        result.simulate(x0=[1.0])


FAST = {"support_steps": 300, "refit_steps": 200}


def test_bad_hidden_terms():
    data = systems.lotka_volterra(n_times=300)
    with pytest.raises(ValueError, match="hidden_terms entries must be"):
        discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=1, include_bias=False),
                        t=data.t, feature_names=["x"], hidden_terms=[("y", "x")],
                        training=FAST, verbose=False)


def test_hidden_names_count():
    data = systems.lotka_volterra(n_times=300)
    with pytest.raises(ValueError, match=r"hidden_names has 2 name\(s\) but 1 hidden state"):
        discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=1, include_bias=False),
                        t=data.t, feature_names=["x"], hidden_names=["a", "b"],
                        hidden_terms=[("x", "x")], training=FAST, verbose=False)


def test_no_hidden_variable_is_an_error():
    data = systems.harmonic_oscillator(A=-2.0, B=1.0, n_times=600, t_end=20)
    with pytest.raises(ValueError, match="No coefficient varies in time"):
        discover_hidden(data.x, ps.PolynomialLibrary(degree=1, include_bias=False), t=data.t,
                        verbose=False)


def test_bad_closure_library():
    data = systems.lotka_volterra(n_times=300)
    with pytest.raises(TypeError, match="closure_library must be a pysindy feature library"):
        discover_hidden(data.x[:, :1], t=data.t, closure_library="poly2", verbose=False)


def test_several_trajectories():
    a = systems.lotka_volterra(n_times=800, t_end=12, x0=(10.0, 5.0))
    b = systems.lotka_volterra(n_times=800, t_end=12, x0=(30.0, 8.0))
    result = discover_hidden([a.x[:, :1], b.x[:, :1]],
                             ps.PolynomialLibrary(degree=1, include_bias=False),
                             t=[a.t, b.t], feature_names=["x"], verbose=False)
    assert len(result.all_hidden) == 2
    assert result.compare_hidden(a.x_clean[:, 1]).r2[0] > 0.99


def test_lotka_volterra_example_runs(tmp_path):
    out = lotka_volterra.main(noise_levels=(0.01,), n_times=600, output=tmp_path,
                              verbose=False)
    assert (tmp_path / "lotka_volterra.png").exists()
    assert out[0.01]["r2"] > 0.9


def test_oscillator_example_runs(tmp_path):
    out = oscillator.main(noise_levels=(0.0,), n_times=600, output=tmp_path, verbose=False)
    assert (tmp_path / "oscillator.png").exists()
    assert len(out[0.0]["result"].hidden_names) == 1
