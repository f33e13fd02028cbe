"""Result files: an exact round trip, and files that are refused without running anything."""

import json

import numpy as np
import pysindy as ps
import pytest
import sympy as sp

from latentsindy import load
from latentsindy._core import saving
from latentsindy._files.expressions import from_tree, to_tree


@pytest.fixture(scope="module")
def saved(tmp_path_factory, lv):
    """The noise-free LV result (conftest's fixture), written once."""
    _, result = lv
    path = tmp_path_factory.mktemp("files") / "lv.npz"
    result.save(path)
    return result, path


def test_round_trip_is_exact(saved):
    result, path = saved
    back = load(path)
    assert back.state_names == result.state_names
    assert back.hidden_states == result.hidden_states
    for a, b in zip(back.terms, result.terms, strict=True):
        assert (a.state, a.feature, a.value, a.fixed) == (b.state, b.feature, b.value, b.fixed)
        assert a.stderr == b.stderr or (np.isnan(a.stderr) and np.isnan(b.stderr))
    assert back.summary() == result.summary()
    assert back.to_latex() == result.to_latex()
    np.testing.assert_array_equal(back.hidden, result.hidden)
    np.testing.assert_array_equal(back.hidden_std, result.hidden_std)
    np.testing.assert_array_equal(back.coefficients.mean, result.coefficients.mean)
    np.testing.assert_array_equal(back.coefficients.lower, result.coefficients.lower)
    np.testing.assert_array_equal(back.coefficients.upper, result.coefficients.upper)
    assert back.coefficients.doubts == result.coefficients.doubts
    np.testing.assert_array_equal(back.initial_state, result.initial_state)
    assert back.refinement == result.refinement
    assert back.doubts == result.doubts and back.confident == result.confident
    assert result.data_use is not None and back.data_use == result.data_use
    np.testing.assert_array_equal(back.coefficients.times, result.coefficients.times)
    assert len(back.alternatives) == len(result.alternatives)
    for a, b in zip(back.alternatives, result.alternatives, strict=True):
        assert (a.description, a.status, a.size) == (b.description, b.status, b.size)
        assert all(sp.expand(a.rhs[n] - b.rhs[n]) == 0 for n in b.rhs)


def test_doubts_round_trip_and_version_2_files_load(saved, tmp_path):
    """A result's doubts survive the round trip; a version-2 file (written before
    results carried their checks) loads, doubted for that reason, so not confident."""
    import dataclasses

    result, _ = saved
    doubted = dataclasses.replace(result, doubts=("a check failed",))
    path = tmp_path / "doubted.npz"
    doubted.save(path)
    back = load(path)
    assert back.doubts == ("a check failed",) and not back.confident
    assert "DOUBT: a check failed" in back.summary()

    def to_version_2(meta):
        meta["version"] = 2
        del meta["doubts"]

    _rewrite(path, tmp_path / "v2.npz", to_version_2)
    old = load(tmp_path / "v2.npz")
    assert len(old.doubts) == 1 and "did not record the checks" in old.doubts[0]
    assert not old.confident and old.data_use is None


def test_expression_trees_round_trip():
    x, h = sp.symbols("x h", real=True)
    expr = sp.Float(0.25) * x**3 - sp.Rational(1, 3) * h * sp.sin(x) + 7
    assert from_tree(json.loads(json.dumps(to_tree(expr))), {"x": x, "h": h}) == expr
    with pytest.raises(ValueError, match="Cannot store the expression"):
        to_tree(sp.Symbol("x") + sp.Function("f")(sp.Symbol("x")))


def _rewrite(path, target, edit):
    with np.load(path) as data:
        arrays = {k: data[k] for k in data.files}
    meta = json.loads(str(arrays["meta"]))
    edit(meta)
    arrays["meta"] = np.array(json.dumps(meta))
    np.savez(target, **arrays)


CODE = "__import__('os').system('touch {marker}')"


@pytest.mark.parametrize("edit, message", [
    (lambda m, c: m["terms"][0].__setitem__("feature", ["Symbol", c]), "unknown symbol"),
    (lambda m, c: m["terms"][0].__setitem__("feature", ["Function", c, []]),
     "is not allowed"),
    (lambda m, c: m["terms"][0].__setitem__("feature", ["Lambda", c]), "is not allowed"),
    (lambda m, c: m["terms"][0].__setitem__("value", c), "not a number"),
    (lambda m, c: m["terms"][0].__setitem__("feature", ["Integer", c]), "not an integer"),
    (lambda m, c: m.__setitem__("hidden_names", [c]), "list of identifiers"),
    (lambda m, c: m["terms"][0].__setitem__("state", c), "unknown state"),
    (lambda m, c: m["hidden_states"][0].__setitem__("name", c), "not among the result"),
], ids=["symbol", "function", "node", "value", "integer", "names", "state", "hidden"])
def test_crafted_files_are_refused_and_run_nothing(saved, tmp_path, edit, message):
    """Code placed in a text field of the file is refused with a ValueError that names
    the file; nothing is executed (the marker file the code would create never
    appears)."""
    _, path = saved
    marker = tmp_path / "executed"
    bad = tmp_path / "crafted.npz"
    _rewrite(path, bad, lambda m: edit(m, CODE.format(marker=marker)))
    with pytest.raises(ValueError, match=message) as info:
        load(bad)
    assert str(bad) in str(info.value)
    assert not marker.exists()


def test_other_files_are_refused(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, meta=np.array('{"format": "something"}'))
    with pytest.raises(ValueError, match="not a saved HiddenDiscovery"):
        load(path)
    broken = tmp_path / "broken.npz"
    broken.write_bytes(b"not a zip file")
    with pytest.raises(ValueError, match="broken.npz cannot be loaded"):
        load(broken)
    with pytest.raises(FileNotFoundError, match=r"nothing\.npz: no such file \(expected the "
                       r"\.npz written by HiddenDiscovery\.save"):
        load(tmp_path / "nothing.npz")
    with pytest.raises(FileNotFoundError, match="no such file"):
        load(tmp_path)  # a folder


def test_only_result_types_have_a_file_format(tmp_path):
    """Results reach their format through one hook; anything else is refused by name
    and nothing is written."""
    path = tmp_path / "x.npz"
    with pytest.raises(TypeError, match="no file format for dict objects"):
        saving.save({"a": 1}, path)
    assert not path.exists()


def test_missing_entries_are_refused(saved, tmp_path):
    _, path = saved
    bad = tmp_path / "partial.npz"
    _rewrite(path, bad, lambda m: m.pop("terms"))
    with pytest.raises(ValueError, match="missing or malformed entry"):
        load(bad)


@pytest.mark.parametrize("generator, training", [
    ("timevae", {"support_steps": 40, "refit_steps": 40}),
    ("hypersindy", {"support_steps": 2, "refit_steps": 1, "min_epochs": 1, "window": 200}),
    ("hypersindy", {"mode": "online", "support_steps": 2, "refit_steps": 1, "window": 200,
                    "online_steps": 1}),
], ids=["timevae", "hypersindy", "hypersindy-online"])
def test_fitted_model_round_trip_gives_the_same_coefficients(generator, training, tmp_path):
    """A fitted DynamicSINDy, saved and loaded (weights as plain arrays, network rebuilt
    from its settings), gives bit-identical coefficients, samples and predictions."""
    from latentsindy import DynamicSINDy, systems

    data = systems.harmonic_oscillator(n_times=400)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), generator=generator,
                         training=training, verbose=False, seed=4)
    model.fit(data.x, data.t, feature_names=["x", "y"])
    model.save(tmp_path / "model.npz")
    back = load(tmp_path / "model.npz")
    assert isinstance(back, DynamicSINDy)
    a, b = model.coefficients(n_samples=5), back.coefficients(n_samples=5)
    np.testing.assert_array_equal(a.mean, b.mean)
    np.testing.assert_array_equal(a.samples, b.samples)
    assert (a.state_names, a.feature_names) == (b.state_names, b.feature_names)
    np.testing.assert_array_equal(a.support, b.support)
    np.testing.assert_array_equal(a.lower, b.lower)
    np.testing.assert_array_equal(a.upper, b.upper)
    assert a.doubts == b.doubts == model.doubts_ == back.doubts_
    np.testing.assert_array_equal(model.predict()[0], back.predict()[0])
    assert back.get_params()["generator"] == generator


def test_model_files_without_library_or_with_wrong_weights(tmp_path):
    """A custom library is not stored: the loaded model gives coefficients and says why
    predict() cannot run; weights that do not fit the network are refused."""
    from latentsindy import DynamicSINDy, systems

    data = systems.harmonic_oscillator(n_times=300)
    library = ps.CustomLibrary([lambda u: u, lambda u: u**3])
    model = DynamicSINDy(library, training={"support_steps": 20, "refit_steps": 20},
                         verbose=False).fit(data.x, data.t)
    model.save(tmp_path / "m.npz")
    back = load(tmp_path / "m.npz")
    np.testing.assert_array_equal(back.coefficients(2).mean, model.coefficients(2).mean)
    with pytest.raises(RuntimeError, match="without its feature library"):
        back.predict()
    with np.load(tmp_path / "m.npz") as f:
        arrays = {k: f[k] for k in f.files}
    key = next(k for k in arrays if k.startswith("weight:") and arrays[k].ndim == 2)
    arrays[key] = arrays[key][:, :1]
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(ValueError, match=r"bad\.npz cannot be loaded: .*size mismatch"):
        load(tmp_path / "bad.npz")


def test_model_files_before_version_3_read_every_sample(tmp_path):
    """Files written before timeVAE's encoder averaged a long series down to its knots
    hold an encoder trained on every sample: loaded, it reads every sample again (the
    coefficients those files were saved with), while a current file reads the average."""
    from latentsindy import DynamicSINDy, systems

    data = systems.harmonic_oscillator(n_times=600, noise=0.01)  # longer than 256 knots
    # the generator decides the structure: every term stays time-varying after 40 steps
    # (256 knots set: such files were built from their settings, versions < 4)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=1), structure="generator", verbose=False,
                         generator_options={"n_knots": 256},
                         training={"support_steps": 20, "refit_steps": 20}).fit(data.x, data.t)
    model.save(tmp_path / "m.npz")
    pooled = model.coefficients(4).samples
    np.testing.assert_array_equal(load(tmp_path / "m.npz").coefficients(4).samples, pooled)

    def to_version_2(meta):
        meta["version"] = 2
        del meta["generator_options_used"]

    _rewrite(tmp_path / "m.npz", tmp_path / "v2.npz", to_version_2)
    old = load(tmp_path / "v2.npz")
    assert old.model_.generator.encoder_points is None
    model.model_.generator.encoder_points = None  # what the old code computed
    every = model.coefficients(4).samples
    assert np.abs(every - pooled).max() > 0
    np.testing.assert_array_equal(old.coefficients(4).samples, every)


def test_model_files_keep_the_knots_chosen_from_the_data(tmp_path):
    """A model whose timeVAE knots were chosen from the data (version 4) loads with
    them and gives the same coefficients; a version-3 file (built from its settings:
    256 knots when unset) loads with 256 knots, as it was trained."""
    from latentsindy import DynamicSINDy, systems

    data = systems.lotka_volterra(n_times=1000, noise=0.01)
    short = {"support_steps": 10, "refit_steps": 10}
    lib = ps.PolynomialLibrary(degree=2)
    model = DynamicSINDy(lib, verbose=False, training=short).fit(data.x[:, :1], data.t)
    assert model.generator_options_.n_knots < 256  # the noise leaves fewer resolved
    model.save(tmp_path / "m.npz")
    back = load(tmp_path / "m.npz")
    assert back.generator_options_ == model.generator_options_
    np.testing.assert_array_equal(back.coefficients(4).samples, model.coefficients(4).samples)

    clean = systems.lotka_volterra(n_times=1000)
    old = DynamicSINDy(lib, verbose=False, training=short).fit(clean.x[:, :1], clean.t)
    assert old.generator_options_.n_knots == 256 and old.generator_options is None
    old.save(tmp_path / "old.npz")

    def to_version_3(meta):
        meta["version"] = 3
        del meta["generator_options_used"]

    _rewrite(tmp_path / "old.npz", tmp_path / "v3.npz", to_version_3)
    back = load(tmp_path / "v3.npz")
    assert back.generator_options_.n_knots == 256
    np.testing.assert_array_equal(back.coefficients(4).samples, old.coefficients(4).samples)
    # a version-3 file whose settings named its knots is built with them
    set_knots = DynamicSINDy(lib, verbose=False, training=short,
                             generator_options={"n_knots": 64}).fit(clean.x[:, :1], clean.t)
    set_knots.save(tmp_path / "set.npz")
    _rewrite(tmp_path / "set.npz", tmp_path / "set3.npz", to_version_3)
    back = load(tmp_path / "set3.npz")
    assert back.generator_options_.n_knots == 64
    np.testing.assert_array_equal(back.coefficients(4).samples,
                                  set_knots.coefficients(4).samples)
