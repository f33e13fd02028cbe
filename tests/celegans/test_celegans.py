"""The C. elegans workflow: loaders for both layouts, the switch, fixed points, the fit."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from latentsindy import celegans

ROOT = Path(__file__).resolve().parents[2]


def _example():
    spec = importlib.util.spec_from_file_location("c_elegans", ROOT / "examples" / "c_elegans.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ------------------------------------------------------------------ two-level switch
def test_two_level_switch_recovers_pieces_and_levels():
    rng = np.random.default_rng(0)
    t = np.arange(1000) * 0.5
    truth = np.array([100.0, 180.0, 333.0])  # switch times
    labels = np.searchsorted(truth, t, side="right") % 2
    u = np.where(labels == 1, 0.044, -0.266) + rng.normal(scale=0.05, size=t.size)
    sw = celegans.two_level_switch(u, t)
    np.testing.assert_allclose(sw.switch_times, truth, atol=1.0)  # two samples
    np.testing.assert_allclose(sw.levels, [-0.266, 0.044], atol=0.01)
    assert np.array_equal(sw.at([0.0, 150.0, 200.0, 499.0]), sw.levels[[0, 1, 0, 1]])


def test_two_level_switch_constant_series_has_no_switch():
    sw = celegans.two_level_switch(np.full(50, 2.0), np.arange(50.0))
    assert sw.switch_times.size == 0 and np.allclose(sw.values, 2.0)


@pytest.mark.parametrize("u, t, kw, match", [
    (np.zeros(10), np.arange(9.0), {}, "same length"),
    (np.array([0.0, np.nan, 1.0, 2.0, 3.0]), np.arange(5.0), {}, "NaN"),
    (np.zeros(10), np.arange(10.0), {"penalty": -1.0}, "penalty must be >= 0"),
])
def test_two_level_switch_errors(u, t, kw, match):
    with pytest.raises(ValueError, match=match):
        celegans.two_level_switch(u, t, **kw)


def test_sigmoid_switch_is_the_papers_recipe():
    u = np.array([-1.0, -1.0, 1.0, 1.0, -1.0])
    assert np.allclose(celegans.sigmoid_switch(u), u + 0.0, atol=1e-12)


# ------------------------------------------------------------------ fixed points
def test_fixed_points_match_the_papers_bistability_argument():
    """Supplement 3.1: one stable point at -5.25 for u0; -2.32 and 7.88 stable, -1.19
    unstable for u1."""
    low = celegans.fixed_points(celegans.PAPER_CUBIC, -0.266)
    assert [round(p.x, 2) for p in low] == [-5.25] and low[0].stable
    high = celegans.fixed_points(celegans.PAPER_CUBIC, 0.044)
    np.testing.assert_allclose([p.x for p in high], [-2.32, -1.19, 7.88], atol=0.01)
    assert [p.stable for p in high] == [True, False, True]
    saddle = high[1]
    assert max(e.real for e in saddle.eigenvalues) > 0 > min(e.real for e in saddle.eigenvalues)


# ------------------------------------------------------------------ files
@pytest.fixture(scope="module")
def two_worms():
    return [celegans.switching_worm(n_frames=400, n_neurons=12, seed=s, name=n)[0]
            for s, n in ((1, "TS_b"), (2, "TS_a"))]


def _same(a, b):
    assert a.name == b.name and a.fps == b.fps and a.neuron_names == b.neuron_names
    np.testing.assert_array_equal(a.traces, b.traces)
    np.testing.assert_array_equal(a.t, b.t)
    names_a = [a.state_names[k] for k in a.states]
    names_b = [b.state_names[k].replace("_", " ") for k in b.states]
    assert names_a == names_b


def test_v5_folder_round_trip(tmp_path, two_worms):
    files = celegans.write_kato_folder(tmp_path / "wbdata", two_worms)
    assert [f.name for f in files] == ["TS_a.mat", "TS_b.mat"]
    loaded = {r.name: r for r in celegans.load_kato(tmp_path / "wbdata")}
    for rec in two_worms:
        _same(rec, loaded[rec.name])
    one = celegans.load_kato(files[1])  # one file: labels found beside it
    _same(two_worms[0], one[0])


def test_v73_round_trip(tmp_path, two_worms):
    path = celegans.write_wt_nostim(tmp_path / "WT_NoStim.mat", two_worms)
    assert path.read_bytes()[:19] == b"MATLAB 7.3 MAT-file"
    loaded = celegans.load_kato(path)
    assert [r.name for r in loaded] == ["TS_b", "TS_a"]
    for rec, back in zip(two_worms, loaded, strict=True):
        _same(rec, back)


def test_loader_errors(tmp_path, two_worms):
    from scipy.io import savemat

    with pytest.raises(ValueError, match="missing.mat: no such file or folder. Pass "
                                         "WT_NoStim.mat"):
        celegans.load_kato(tmp_path / "missing.mat")
    (tmp_path / "junk.mat").write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(ValueError, match="junk.mat: not a readable MATLAB v5 file"):
        celegans.load_kato(tmp_path / "junk.mat")
    savemat(tmp_path / "other.mat", {"foo": np.ones(3)})
    with pytest.raises(ValueError, match="no struct 'wbData'; variables are \\['foo'\\]"):
        celegans.load_kato_worm(tmp_path / "other.mat")
    savemat(tmp_path / "partial.mat", {"wbData": {"deltaFOverF": np.ones((60, 3)),
                                                  "fps": 2.8}})
    with pytest.raises(ValueError, match="partial.mat: 'wbData' has no field 'tv'"):
        celegans.load_kato_worm(tmp_path / "partial.mat")
    with pytest.raises(ValueError, match="no field 'traces'"):
        celegans.load_kato_worm(tmp_path / "partial.mat", trace="traces")
    with pytest.raises(ValueError, match="not a MATLAB v7.3"):
        celegans.load_wt_nostim(tmp_path / "other.mat")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no per-worm .mat files"):
        celegans.load_kato(tmp_path / "empty")
    celegans.write_kato_folder(tmp_path / "wb", two_worms)
    with pytest.raises(ValueError, match="labels for 2 worms; asked for worm 5"):
        celegans.load_kato_worm(tmp_path / "wb" / "TS_a.mat",
                                labels=tmp_path / "wb" / "sevenStateColoring.mat",
                                labels_index=5)


def test_folder_skips_other_files_and_tolerates_foreign_labels(tmp_path, two_worms):
    from scipy.io import savemat

    folder = tmp_path / "wbdata"
    celegans.write_kato_folder(folder, two_worms)
    savemat(folder / "AAA_notes.mat", {"notes": np.ones(3)})  # sorts first; not a worm
    celegans.write_wt_nostim(folder / "WT_NoStim.mat", two_worms)
    loaded = celegans.load_kato(folder)
    assert [r.name for r in loaded] == ["TS_a", "TS_b"]
    assert all(r.states is not None for r in loaded)
    other = [celegans.switching_worm(n_frames=300, n_neurons=5, seed=9, name="X")[0]]
    celegans.write_kato_folder(tmp_path / "labels_only", other)  # 300 labels, not 400
    (tmp_path / "labels_only" / "sevenStateColoring.mat").replace(
        folder / "sevenStateColoring.mat")
    with pytest.warns(UserWarning, match="without behaviour labels"):
        loaded = celegans.load_kato(folder)
    assert all(r.states is None for r in loaded)


def test_v73_file_with_another_layout_is_refused(tmp_path):
    import h5py

    with h5py.File(tmp_path / "odd.mat", "w") as f:
        g = f.create_group("data")
        g.create_dataset("deltaFOverF", data=np.ones((3, 60)))
        g.create_dataset("tv", data=np.arange(60.0))
        g.create_dataset("fps", data=2.8)
    with pytest.raises(ValueError, match="odd.mat: struct 'data' is not laid out like "
                                         "WT_NoStim.mat"):
        celegans.load_kato(tmp_path / "odd.mat")


def test_recording_validation_and_component():
    t = np.arange(100) / 2.8
    with pytest.raises(ValueError, match="traces must be \\(n_frames, n_neurons\\)"):
        celegans.WormRecording("w", t, np.ones((99, 3)), ("", "", ""), 2.8)
    with pytest.raises(ValueError, match="2 neuron names for 3 traces"):
        celegans.WormRecording("w", t, np.ones((100, 3)), ("", ""), 2.8)
    rng = np.random.default_rng(0)
    x = np.sin(t)
    axis = np.array([0.6, 0.8, 0.0])
    rec = celegans.WormRecording("w", t, np.outer(x, axis) + 1e-6 * rng.normal(size=(100, 3)),
                                 ("A", "", "B"), 2.8)
    comp = rec.first_component()
    np.testing.assert_allclose(comp.x, x, atol=1e-5)  # uncentred projection: x itself
    np.testing.assert_allclose(comp.loadings, axis, atol=1e-5)
    assert comp.explained > 0.999
    np.testing.assert_allclose(rec.first_component(center=True).x, x - x.mean(), atol=1e-5)


# ------------------------------------------------------------------ the workflow
def test_fit_errors():
    with pytest.raises(TypeError, match="expected a WormRecording or a Component; got ndarray"):
        celegans.fit_switching_model(np.zeros(10))
    with pytest.raises(ValueError, match="data is empty"):
        celegans.fit_switching_model([])
    rec = celegans.switching_worm(n_frames=60, n_neurons=5, seed=0)[0]
    with pytest.raises(ValueError, match="test_half_width must be an int >= 2"):
        celegans.fit_switching_model(rec, stage_one=False, test_half_width=1)
    with pytest.raises(ValueError, match="need at least 82 frames per worm; the shortest "
                                         "worm has 60"):
        celegans.fit_switching_model(rec, stage_one=False, test_half_width=20)


def test_shared_cubic_and_per_worm_levels_without_stage_one():
    """Two worms, different inputs, one cubic: shared constants within 10%, each worm's
    own levels within 10%, switch times within 2% of the series."""
    worms = [celegans.switching_worm(n_frames=2000, seed=3, levels=(-0.266, 0.044)),
             celegans.switching_worm(n_frames=2000, seed=4, levels=(-0.3, 0.06))]
    model = celegans.fit_switching_model([w[0] for w in worms], stage_one=False)
    assert model.converged
    for k, v in celegans.PAPER_CUBIC.items():
        assert abs(model.cubic[k] / v - 1) < 0.10, (k, model.cubic[k])
    for fit, (_, truth) in zip(model.worms, worms, strict=True):
        np.testing.assert_allclose(fit.switch.levels, truth.levels, rtol=0.10)
        inside = truth.switch_times[truth.switch_times < fit.t[-5]]
        assert fit.switch.switch_times.size == inside.size
        assert np.max(np.abs(fit.switch.switch_times - inside)) < 0.02 * fit.t[-1]
    eq = model.equations()
    assert str(eq[0].rhs) == "y" and "u" in str(eq[1].rhs)


@pytest.mark.parametrize("layout", ["v5", "v7.3"])
def test_example_recovers_switches_and_cubic(tmp_path, layout):
    """Done-when bar of issue 11: switch times within 2% of the series length and the
    cubic's coefficients within 10%, through stage one, from files of either layout."""
    report = _example().main(layout=layout, output=tmp_path)
    assert max(report["coefficient_errors"].values()) < 0.10
    assert max(report["switch_errors"]) < 0.02
    assert report["figure"].exists() and report["figure"].stat().st_size > 10_000
    worm = report["model"].worms[0]
    assert [len(points) for _, points in worm.fixed_points] == [1, 3]
