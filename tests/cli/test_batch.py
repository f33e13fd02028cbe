"""Many recordings at once: two workers give what one-by-one calls give, failures are
recorded, and the command line runs a folder into one table."""

import csv
import io

import numpy as np
import pysindy as ps
import pytest

from latentsindy import discover_hidden, discover_many, load, systems
from latentsindy._cli.main import main

LIBRARY = ps.PolynomialLibrary(degree=3, include_bias=False)


@pytest.fixture(scope="module")
def recordings():
    """Prey-only Lotka-Volterra, two noise realisations at 1%, T=800."""
    out = {}
    for seed in (1, 2):
        data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=800, t_end=16.0,
                                      noise=0.01, seed=seed)
        out[f"worm{seed}"] = (data.t, data.x[:, :1])
    return out


def test_two_workers_give_the_one_by_one_results(recordings):
    runs = discover_many({k: x for k, (_, x) in recordings.items()}, LIBRARY,
                         t={k: t for k, (t, _) in recordings.items()}, n_jobs=2,
                         feature_names=["x"])
    assert [r.name for r in runs] == ["worm1", "worm2"]
    for run in runs:
        t, x = recordings[run.name]
        alone = discover_hidden(x, LIBRARY, t=t, feature_names=["x"], verbose=False)
        assert run.error is None and run.wall > 0
        assert [(a.state, a.feature) for a in run.result.terms] == \
            [(a.state, a.feature) for a in alone.terms]
        np.testing.assert_allclose([a.value for a in run.result.terms],
                                   [a.value for a in alone.terms], rtol=1e-6)
        row = run.row()
        assert row["hidden_states"] == 1 and row["error"] == ""


def test_a_failed_run_is_recorded_and_the_others_go_on(recordings):
    t, x = recordings["worm1"]
    runs = discover_many({"good": x, "flat": np.ones_like(x)}, LIBRARY, t=t,
                         feature_names=["x"])
    good, flat = runs
    assert good.error is None and flat.result is None
    assert flat.error.startswith("ValueError") and flat.row()["hidden_states"] == ""
    with pytest.raises(TypeError, match="use seeds="):
        discover_many([x], LIBRARY, t=t, seed=3)
    with pytest.raises(ValueError, match=r"t has no entry for recording\(s\) \['1'\]"):
        discover_many([x, x], LIBRARY, t={"0": t})


def test_command_line_runs_a_folder_into_one_table(recordings, tmp_path, capsys):
    folder = tmp_path / "data"
    folder.mkdir()
    for name, (t, x) in recordings.items():
        np.savetxt(folder / f"{name}.csv", np.column_stack([t, x]), delimiter=",",
                   header="t,x", comments="")
    code = main(["discover", str(folder), "--time", "t", "--observed", "x",
                 "--library", "poly:3:nobias", "--jobs", "2", "--out", str(tmp_path / "out"),
                 "--quiet"])
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["name"] for r in rows] == ["worm1", "worm2"]
    assert all(r["hidden_states"] == "1" and r["error"] == "" for r in rows)
    assert load(tmp_path / "out" / "worm2.npz").hidden_names == ("h0",)
    assert main(["discover", str(tmp_path / "*.nothing"), "--time", "t", "--observed", "x",
                 "--quiet"]) == 2
    assert "no data files" in capsys.readouterr().err
