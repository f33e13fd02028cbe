"""Stage two: discover_hidden on the tutorials, the result object and its checks."""

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pysindy as ps
import pytest
import sympy as sp
import torch

from latentsindy import HiddenDiscovery, discover_hidden, systems
from latentsindy.results import HiddenState, Term

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "examples"))
import lorenz_from_x  # noqa: E402
import lotka_volterra  # noqa: E402
import oscillator  # noqa: E402

X, H = sp.symbols("x h", real=True)


def test_lv_hidden_state_and_equation(lv):
    """Exact data: exact structure, hidden-equation coefficients within 0.1% (measured
    0.01%), the hidden state is the coefficient of x in dx/dt."""
    data, result = lv
    assert isinstance(result, HiddenDiscovery)
    assert result.state_names == ("x", "h")
    assert result.hidden_states == (HiddenState("h", (("x", "x"),)),)
    assert result.hidden_terms == ((("x", "x"),),)
    assert result.compare_hidden(data.x_clean[:, 1]).r2[0] >= 0.9999
    errors, extra, missing = lotka_volterra.equation_errors(result.equation("h"),
                                                            lotka_volterra.TRUE_HIDDEN)
    assert extra == [] and missing == []
    assert max(errors.values()) <= 1e-3
    assert sp.expand(result.rhs["x"] - X * H) == 0
    assert result.uncertain == ()


def test_lv_hidden_equation_has_standard_errors(lv):
    """Every estimated hidden-equation coefficient carries a finite standard error that
    covers its (tiny, on exact data) error; the definition xdot = h x is fixed."""
    _, result = lv
    hidden = [t for t in result.terms if t.state == "h"]
    assert len(hidden) == 4 and all(not t.fixed and np.isfinite(t.stderr) for t in hidden)
    definition = [t for t in result.terms if t.state == "x"]
    assert len(definition) == 1 and definition[0].fixed and definition[0].value == 1.0
    truth = lotka_volterra.TRUE_HIDDEN
    for t in hidden:
        assert abs(t.value - truth[t.feature]) <= max(10 * t.stderr, 1e-3 * abs(truth[t.feature]))


def test_lv_refinement_is_reported(lv):
    _, result = lv
    r = result.refinement
    assert r is not None and r.misfit_after < r.misfit_before and r.misfit_after < 1e-3
    assert r.continuity_gap < 0.1
    assert result.score < 0.05  # exact data: held-out misfit far below the noise floor
    text = result.summary()
    assert "h = coefficient of x in dx/dt" in text
    assert "refined by integration" in text and "+-" in text
    # where the time went: every stage ran, each a positive share
    assert {"differentiation", "stage one: generator", "proposals", "closure", "refinement",
            "term selection", "held-out score", "other"} <= set(result.timings)
    assert all(v > 0 for v in result.timings.values())


def test_lv_with_one_percent_noise():
    """Issue 9 bars on the tutorial at 1% noise: hidden-equation coefficients within
    0.5% (measured 0.06%), exact structure, and the closed system reproduces the prey
    with normalised RMSE <= 0.05 (measured 0.010, the noise level)."""
    out = lotka_volterra.main(noise_levels=(0.01,), output=None, verbose=False)[0.01]
    assert out["extra"] == [] and out["missing"] == []
    assert max(out["errors"].values()) <= 0.005
    assert out["r2"] >= 0.999
    assert out["nrmse"] <= 0.05


def test_lorenz_from_x_tutorial(tmp_path):
    """The two-hidden-variable tutorial at its own settings (sigma 10, rho 28, beta 8/3,
    1% noise): the law in the variables found, no extra or missing term, coefficients
    within 2%, y and z recovered with R^2 >= 0.95 (issue 20's bar), confident, and a
    figure written."""
    out = lorenz_from_x.main(output=tmp_path, verbose=False)
    assert out["extra"] == [] and out["missing"] == [], out
    assert max(out["errors"].values()) <= 0.02
    assert min(out["r2"]) >= 0.95
    assert out["result"].confident
    assert (tmp_path / "lorenz_from_x.png").stat().st_size > 0


def test_lv_affine_map_recovers_predator(lv):
    data, result = lv
    cmp = result.compare_hidden(data.x_clean[:, 1])
    # y = (alpha - h) / beta  ->  scale -1/beta = -10, offset alpha/beta = 10
    assert cmp.scale[0, 0] == pytest.approx(-10.0, rel=1e-3)
    assert cmp.offset[0] == pytest.approx(10.0, rel=1e-3)


def test_vector_field_numpy_and_torch_agree(lv):
    _, result = lv
    field = result.vector_field()
    y = result.states[::100]
    np.testing.assert_allclose(field(0.0, torch.as_tensor(y)).numpy(), field(0.0, y), rtol=1e-12)


def test_reported_hidden_series_is_the_closed_systems_trajectory(lv):
    """With refinement the hidden series is the closed system's own trajectory: its
    derivative matches the hidden equation evaluated on the reported states."""
    _, result = lv
    rate = np.gradient(result.hidden[:, 0], result.times)
    model = result.vector_field()(0.0, result.states)[:, 1]
    inner = slice(50, -50)
    assert np.max(np.abs(rate[inner] - model[inner])) < 1e-3 * np.max(np.abs(model))


def test_simulation_reproduces_observed(lv):
    data, result = lv
    sim = result.simulate()
    assert sim.success, sim.message
    nrmse = np.sqrt(np.mean((sim.x[:, 0] - data.x[:, 0]) ** 2)) / np.std(data.x[:, 0])
    assert nrmse < 1e-3


def test_blow_up_is_reported_not_hung(lv):
    _, result = lv
    sim = result.simulate(t=np.linspace(0, 50, 100), x0=[1e4, 50.0])
    assert sim.status in {"blow_up", "step_budget"}
    assert "x0" in sim.message or "max_steps" in sim.message
    np.testing.assert_array_equal(sim.x[0], [1e4, 50.0])  # the rows before it are kept
    assert np.all(np.isnan(sim.x[-1]))


def test_summary_and_latex(lv):
    _, result = lv
    assert r"\dot{x} &= 1.0 h x" in result.to_latex()
    assert len(result.equations) == 2
    assert result.coefficient("x", "h*x") == 1.0
    assert result.coefficient("h", "x**2") == 0.0


def test_compare_hidden_map_uses_the_terms_a_hidden_state_absorbs(lv):
    """A hidden state that is the coefficient of x in dx/dt is the true coefficient less
    g / x for every observed term g of dx/dt that x divides (Van der Pol seen through x:
    h = y - mu (x - x^3 / 3)). With x^3 and a constant beside x h, the map may use x and
    x^2 (not 1 / x) and recovers 2 h + 0.7 x^2 + 1 exactly; without them it cannot."""
    _, result = lv
    x = X
    extra = (Term("x", x**3, 0.4, math.nan, False), Term("x", sp.Integer(1), 0.1, math.nan,
                                                         False))
    shown = dataclasses.replace(result, terms=result.terms + extra)
    truth = 2.0 * shown.hidden[:, 0] + 0.7 * shown.observed[:, 0] ** 2 + 1.0
    cmp = shown.compare_hidden(truth, with_observed=True)
    assert cmp.observed_terms == (x, x**2)
    np.testing.assert_allclose(cmp.r2, [1.0], atol=1e-12)
    np.testing.assert_allclose([cmp.scale[0, 0], *cmp.observed_scale[:, 0], cmp.offset[0]],
                               [2.0, 0.0, 0.7, 1.0], atol=1e-8)
    assert result.compare_hidden(truth, with_observed=True).r2[0] < 0.999
    assert result.compare_hidden(truth, with_observed=True).observed_terms == (x,)


def test_a_law_that_blows_up_over_the_recording_is_a_doubt(lv):
    """The free run: the found LV law integrated over the whole recording stays bounded
    (no doubt); the same result with dh/dt = h^2 (h0 > 0 blows up in finite time, at
    t = 1 / h0, inside the recording) gets the doubt that says so."""
    from latentsindy._stage_two.doubts.runs import free_run_doubt

    _, result = lv
    trajectories = [np.hstack([o, h]) for o, h in zip(result.all_observed, result.all_hidden,
                                                       strict=True)]
    assert free_run_doubt(result, trajectories) == ()
    assert result.hidden[0, 0] > 1.0 / (result.times[-1] - result.times[0])
    law = tuple(t for t in result.terms if t.state != "h") + (
        Term("h", H**2, 1.0, math.nan, False),)
    doubt = free_run_doubt(dataclasses.replace(result, terms=law), trajectories)
    assert len(doubt) == 1 and "the closed system blows up" in doubt[0]


def test_compare_hidden_length_mismatch(lv):
    _, result = lv
    with pytest.raises(ValueError, match="true_hidden has 10 rows"):
        result.compare_hidden(np.zeros(10))


def test_compare_hidden_with_observed_states_in_the_map(lv):
    """A truth that is the hidden state shifted by an observed one (true = 3 h - 2 x + 1)
    is recovered exactly only when the map may use the observed states."""
    _, result = lv
    truth = 3.0 * result.hidden[:, 0] - 2.0 * result.observed[:, 0] + 1.0
    assert result.compare_hidden(truth).r2[0] < 0.9
    cmp = result.compare_hidden(truth, with_observed=True)
    np.testing.assert_allclose(cmp.r2, [1.0], atol=1e-12)
    np.testing.assert_allclose([cmp.scale[0, 0], cmp.observed_scale[0, 0], cmp.offset[0]],
                               [3.0, -2.0, 1.0], atol=1e-9)
    assert result.compare_hidden(truth).observed_scale is None
    with pytest.raises(TypeError, match="with_observed must be True or False; got 'yes'"):
        result.compare_hidden(truth, with_observed="yes")


def test_simulate_bad_x0(lv):
    _, result = lv
    with pytest.raises(ValueError, match=r"x0 must have shape \(2,\)"):
        result.simulate(x0=[1.0])


def test_equation_and_coefficient_refuse_unknown_names(lv):
    _, result = lv
    with pytest.raises(ValueError, match="Unknown state 'y'"):
        result.equation("y")
    with pytest.raises(ValueError, match="Unknown state 'y'"):
        result.coefficient("y", "x")
    with pytest.raises(ValueError, match=r"uses \['z'\], which are not states"):
        result.coefficient("h", "h*z")
    assert result.coefficient("h", "x**3") == 0.0  # a known feature that is absent


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


def test_bad_refine_flag():
    data = systems.lotka_volterra(n_times=300)
    with pytest.raises(TypeError, match="refine must be True or False; got 'yes'"):
        discover_hidden(data.x[:, :1], t=data.t, refine="yes", verbose=False)


def test_max_hidden_must_be_a_positive_integer():
    data = systems.lotka_volterra(n_times=300)
    with pytest.raises(ValueError, match="max_hidden must be > 0; got 0"):
        discover_hidden(data.x[:, :1], t=data.t, max_hidden=0, verbose=False)
    with pytest.raises(TypeError, match="max_hidden must be an integer; got 1.5"):
        discover_hidden(data.x[:, :1], t=data.t, max_hidden=1.5, verbose=False)


def test_nothing_hidden_is_an_answer():
    """A fully observed oscillator needs no hidden state: the result has none, its law
    is exact (noise-free data: to 1e-3) and it is confident."""
    data = systems.harmonic_oscillator(A=-2.0, B=1.0, n_times=600, t_end=20)
    result = discover_hidden(data.x, ps.PolynomialLibrary(degree=1, include_bias=False),
                             t=data.t, verbose=False)
    assert result.hidden_names == () and result.hidden.shape == (600, 0)
    assert result.confident, result.summary()
    x0, x1 = sp.symbols("x0 x1", real=True)
    truth = {"x0": {x1: -2.0}, "x1": {x0: 1.0}}  # xdot = A y, ydot = B x
    for state, terms in truth.items():
        found = result.equation(state)
        assert set(found) == set(terms), (state, found)
        for feature, value in terms.items():
            assert abs(found[feature] / value - 1) < 1e-3, (state, feature, found[feature])


def test_both_lotka_volterra_states_observed_at_one_percent_noise():
    """Nothing hidden, 1% noise: zero hidden states, the exact law (coefficients to 1%),
    confident; unrefined, the same structure, not confident (nothing was checked)."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    rng = np.random.default_rng(0)
    x = data.x + 0.01 * data.x.std(axis=0) * rng.standard_normal(data.x.shape)
    library = ps.PolynomialLibrary(degree=2)
    result = discover_hidden(x, library, t=data.t, feature_names=["x", "y"], verbose=False)
    assert result.hidden_names == () and result.confident, result.summary()
    xs, ys = sp.symbols("x y", real=True)
    truth = {"x": {xs: 1.0, xs * ys: -0.1}, "y": {ys: -1.5, xs * ys: 0.075}}
    for state, terms in truth.items():
        found = result.equation(state)
        assert set(found) == set(terms), (state, found)
        for feature, value in terms.items():
            assert abs(found[feature] / value - 1) < 0.01, (state, feature, found[feature])
    rough = discover_hidden(x, library, t=data.t, feature_names=["x", "y"], refine=False,
                            verbose=False)
    assert rough.hidden_names == () and not rough.confident
    assert {s: set(rough.equation(s)) for s in "xy"} == {s: set(t) for s, t in truth.items()}
    assert [d.kind for d in rough.doubts] == ["not checked"]


def test_no_law_found_is_a_result_that_says_so():
    """White noise: no term is kept; the answer has no law (dx/dt = 0), is not
    confident, and its doubt says why."""
    x = np.random.default_rng(0).standard_normal((300, 1))
    result = discover_hidden(x, ps.PolynomialLibrary(degree=2), t=0.1, verbose=False)
    assert result.hidden_names == ()
    assert not result.confident and result.rhs == {"x0": 0}
    assert [d.kind for d in result.doubts] == ["no law"]
    assert "no term of the library was kept" in result.doubts[0]


def test_a_library_with_fourier_features():
    """x' = h + 0.8 sin x, h' = -x seen through x with polynomial and Fourier features:
    the law, term for term (every check on the chosen system takes non-polynomial
    features; the partial-shift check once raised on them)."""
    from scipy.integrate import solve_ivp

    t = np.linspace(0.0, 30.0, 1500)
    sol = solve_ivp(lambda _, s: [s[1] + 0.8 * np.sin(s[0]), -s[0]], (0.0, 30.0), [1.0, 0.0],
                    t_eval=t, rtol=1e-10, atol=1e-12)
    library = ps.PolynomialLibrary(degree=1) + ps.FourierLibrary(n_frequencies=1)
    result = discover_hidden(sol.y[0][:, None], library, t=t, feature_names=["x"],
                             verbose=False, seed=0)
    found = {(term.state, str(term.feature)): term.value for term in result.terms}
    assert set(found) == {("x", "h0"), ("x", "sin(x)"), ("h0", "x")}, found
    assert found["x", "sin(x)"] == pytest.approx(0.8, rel=1e-3)
    assert found["h0", "x"] == pytest.approx(-1.0, rel=1e-3)
    assert not any(d.kind == "partial shift" for d in result.doubts)


def test_bad_closure_library():
    data = systems.lotka_volterra(n_times=300)
    with pytest.raises(TypeError, match="closure_library must be a pysindy feature library.*; "
                                        "got str"):
        discover_hidden(data.x[:, :1], t=data.t, closure_library="poly2", verbose=False)
    with pytest.raises(TypeError, match="closure_library must be a pysindy feature library "
                                        "object; got the class PolynomialLibrary itself"):
        discover_hidden(data.x[:, :1], t=data.t, closure_library=ps.PolynomialLibrary,
                        verbose=False)


def test_several_trajectories():
    """Two prey series from different starts: one closed system, a hidden series each,
    both reproduced (R^2 against each true predator)."""
    a = systems.lotka_volterra(n_times=800, t_end=12, x0=(10.0, 5.0))
    b = systems.lotka_volterra(n_times=800, t_end=12, x0=(30.0, 8.0))
    result = discover_hidden([a.x[:, :1], b.x[:, :1]],
                             ps.PolynomialLibrary(degree=1, include_bias=False),
                             t=[a.t, b.t], feature_names=["x"], verbose=False)
    assert len(result.all_hidden) == 2
    assert result.compare_hidden(a.x_clean[:, 1]).r2[0] > 0.999
    design = np.column_stack([result.all_hidden[1], np.ones(len(b.t))])
    fit = np.linalg.lstsq(design, b.x_clean[:, 1], rcond=None)[0]
    resid = b.x_clean[:, 1] - design @ fit
    assert 1 - resid.var() / b.x_clean[:, 1].var() > 0.999


def test_refinement_can_be_turned_off():
    """refine=False: the closure's coefficients, the structured estimate of the hidden
    series, no refinement record; still the right structure on clean data, coefficients
    within 5% (measured 2.3%; refined: 0.01%)."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=1000, t_end=15)
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=1, include_bias=False),
                             t=data.t, feature_names=["x"], hidden_names=["h"], refine=False,
                             verbose=False)
    assert result.refinement is None and np.isnan(result.score)
    errors, extra, missing = lotka_volterra.equation_errors(result.equation("h"),
                                                            lotka_volterra.TRUE_HIDDEN)
    assert extra == [] and missing == [] and max(errors.values()) < 0.05


def test_lotka_volterra_example_runs(tmp_path):
    out = lotka_volterra.main(noise_levels=(0.01,), n_times=600, output=tmp_path,
                              verbose=False)
    assert (tmp_path / "lotka_volterra.png").exists()
    assert (tmp_path / "lotka_volterra_1pct_result.png").exists()
    assert out[0.01]["r2"] > 0.99


def test_oscillator_example_runs(tmp_path):
    """The oscillator tutorial (noise-free, T=600): one hidden state B with the logistic
    law -6 + 5B - B^2 within 1% (the paper: 2%)."""
    out = oscillator.main(noise_levels=(0.0,), n_times=600, output=tmp_path, verbose=False)
    assert (tmp_path / "oscillator.png").exists()
    assert (tmp_path / "oscillator_0pct_result.png").exists()
    assert (tmp_path / "oscillator_0pct_stage_one.png").exists()
    r = out[0.0]
    assert r["result"].hidden_names == ("B",)
    assert r["extra"] == [] and r["missing"] == []
    assert max(r["errors"].values()) < 0.01


def _competition(noise, seed=0):
    """Two species competing to coexistence, x seen from small populations through one
    rise and settling (15 time units, 2000 samples): ``xdot = x (1 - x - A y)``, ``ydot =
    r y (1 - y - B x)``; y is hidden."""
    from scipy.integrate import solve_ivp
    a, b, r = 0.6133, 0.8093, 1.2161
    t = np.linspace(0.0, 15.0, 2000)
    sol = solve_ivp(lambda _, s: [s[0] * (1 - s[0] - a * s[1]), r * s[1] * (1 - s[1] - b * s[0])],
                    (0.0, 15.0), [0.0755, 0.0293], t_eval=t, rtol=1e-10, atol=1e-10)
    x = sol.y[:1].T
    return t, x + noise * x.std() * np.random.default_rng(seed).standard_normal(x.shape)


def test_nothing_hidden_is_not_confident_where_it_misses_held_out_data(monkeypatch):
    """Stage one sees no coefficient vary, and the logistic law of x alone closes under
    ``MOVES`` on short anchored segments, but scores above 1 + REPRODUCTION_SLACK on
    held-out data: the carriers are judged beside it, and the answer (a logistic law,
    or an approximation with one hidden state) is not confident. It was reported
    confident with no hidden state when the score was read within two standard errors."""
    from latentsindy._stage_two import discover, without_stage_one
    t, x = _competition(0.05, seed=2)
    calls, scores = [], []
    judge_all = discover.judge_all

    def counted(proposals, *args, **kwargs):
        calls.append(len(proposals))
        ordered, uncertain = judge_all(proposals, *args, **kwargs)
        scores.append(ordered[0].cv)
        return ordered, uncertain

    monkeypatch.setattr(discover, "judge_all", counted)
    result = discover_hidden(x, ps.PolynomialLibrary(degree=2), t=t, verbose=False)
    assert calls[0] == 1 and scores[0] > 1 + without_stage_one.REPRODUCTION_SLACK, scores
    assert len(calls) == 2 and calls[1] > 1, calls  # then the carriers, beside it
    assert not result.confident, result.summary()
    # with the law without hidden states taken as it stands (the rule before), the same
    # data gave a wrong answer with confidence: this case is the one the rule is for
    monkeypatch.setattr(without_stage_one, "reproduced", lambda ordered: True)
    before = discover_hidden(x, ps.PolynomialLibrary(degree=2), t=t, verbose=False)
    assert before.hidden_names == () and before.confident, before.summary()
    # a second judgement without a scored winner (max_time spent in it) leaves the first
    monkeypatch.undo()
    monkeypatch.setattr(discover, "judge_all", lambda proposals, *args, **kwargs: (
        judge_all(proposals, *args, **kwargs) if len(proposals) == 1 else ([], [])))
    kept = discover_hidden(x, ps.PolynomialLibrary(degree=2), t=t, verbose=False)
    assert kept.summary() == before.summary()
