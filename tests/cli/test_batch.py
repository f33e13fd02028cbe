"""Many recordings at once: two local workers and a Dask cluster give what one-by-one
calls give, runs are written as they finish, failures (a worker that dies too) are
recorded, and the command line runs a folder into one table."""

import csv
import io
import os
import time

import numpy as np
import pysindy as ps
import pytest

from latentsindy import discover_hidden, discover_many, load, systems
from latentsindy._batch import COLUMNS
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


@pytest.fixture(scope="module")
def alone(recordings):
    """Each recording discovered on its own, in this process."""
    return {name: discover_hidden(x, LIBRARY, t=t, feature_names=["x"], verbose=False)
            for name, (t, x) in recordings.items()}


def _same_as_alone(run, alone):
    assert run.error is None and run.wall > 0
    assert [(a.state, a.feature) for a in run.result.terms] == \
        [(a.state, a.feature) for a in alone[run.name].terms]
    np.testing.assert_allclose([a.value for a in run.result.terms],
                               [a.value for a in alone[run.name].terms], rtol=1e-6)
    row = run.row()
    assert row["hidden_states"] == 1 and row["error"] == ""
    named = set(row["doubts"].split("; ")) - {""}
    assert named == ({d.kind for d in run.result.doubts}
                     | ({"structure uncertain"} if run.result.uncertain else set()))
    assert (row["doubts"] == "") == run.result.confident  # here refined: why, if not


def test_two_workers_give_the_one_by_one_results(recordings, alone):
    runs = discover_many({k: x for k, (_, x) in recordings.items()}, LIBRARY,
                         t={k: t for k, (t, _) in recordings.items()}, n_jobs=2,
                         feature_names=["x"])
    assert [r.name for r in runs] == ["worm1", "worm2"]
    for run in runs:
        _same_as_alone(run, alone)


def test_a_dask_cluster_gives_the_local_results_and_keeps_them_when_a_worker_dies(
        recordings, alone, tmp_path):
    pytest.importorskip("distributed")
    from distributed import LocalCluster

    table = tmp_path / "runs.csv"

    class DiesOnShortRecordings(ps.PolynomialLibrary):
        """Kills the worker process that fits it to a recording of 100 samples, once the
        other runs are written (a task queued on a worker that dies is charged with its
        death too; Dask retries it, but the test should not depend on that)."""

        def fit(self, x, *args, **kwargs):
            if len(x[0]) == 100:
                for _ in range(600):
                    if table.exists() and len(table.read_text().splitlines()) >= 4:
                        break
                    time.sleep(0.1)
                os._exit(1)
            return super().fit(x, *args, **kwargs)

    t = recordings["worm1"][0]
    data = {k: x for k, (_, x) in recordings.items()}
    data |= {"dies": data["worm1"][:100], "short": data["worm1"][:6]}  # 6: too few
    # Dask retries a task whose worker died (three times by default), then reports it
    # as KilledWorker
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        runs = discover_many(data, DiesOnShortRecordings(degree=3, include_bias=False),
                             t={"worm1": t, "worm2": t, "dies": t[:100], "short": t[:6]},
                             scheduler=cluster.scheduler_address, out=tmp_path,
                             feature_names=["x"])
    assert [r.name for r in runs] == ["worm1", "worm2", "dies", "short"]
    for run in runs[:2]:
        _same_as_alone(run, alone)
    dies, short = runs[2:]
    assert dies.result is None and dies.error.startswith("KilledWorker")
    assert short.result is None and short.error.startswith("ValueError: No part of")
    # every run was written as it finished: its row (and its result, if any)
    with open(tmp_path / "runs.csv") as fh:
        rows = {r["name"]: r for r in csv.DictReader(fh)}
    assert set(rows) == {"worm1", "worm2", "dies", "short"}
    assert rows["dies"]["wall_s"] == "" and rows["worm2"]["hidden_states"] == "1"
    assert sorted(p.name for p in tmp_path.glob("*.npz")) == ["worm1.npz", "worm2.npz"]
    assert load(tmp_path / "worm1.npz").hidden_names == ("h0",)
    with pytest.raises(ValueError, match="not both"):
        discover_many(data, LIBRARY, t=t, scheduler="tcp://nowhere:8786", backend="loky")


def test_a_failed_run_is_recorded_and_the_others_go_on(recordings):
    """Local workers: each failure is recorded with its message and the batch goes on
    (a good run beside failures: the Dask test)."""
    t, x = recordings["worm1"]
    runs = discover_many({"unmeasured": np.full_like(x, np.nan), "short": x[:6]}, LIBRARY,
                         t={"unmeasured": t, "short": t[:6]}, feature_names=["x"], n_jobs=2)
    unmeasured, short = runs
    assert unmeasured.result is None and short.result is None
    assert unmeasured.error.startswith("ValueError: x_observed has state column(s) [0] "
                                       "with no finite value")
    assert unmeasured.row()["hidden_states"] == ""
    assert short.error.startswith("ValueError") and "10" in short.error
    with pytest.raises(TypeError, match="use seeds="):
        discover_many([x], LIBRARY, t=t, seed=3)
    with pytest.raises(ValueError, match=r"t has no entry for recording\(s\) \['1'\]"):
        discover_many([x, x], LIBRARY, t={"0": t})


def test_names_and_seeds_that_cannot_be_kept_apart_are_refused_before_any_run(
        recordings, tmp_path):
    t, x = recordings["worm1"]
    with pytest.raises(ValueError, match=r"these cannot: \{'cell 1/trial a': 'a path "
                       r"separator, or a character Windows refuses', '\.\.': 'no name', "
                       r"'CON': 'a name Windows reserves.*'\}\. Rename them, e\.g\. "
                       r"\['cell 1_trial a', 'run', 'CON_'\]"):
        discover_many({"fine": x, "cell 1/trial a": x, "..": x, "CON": x}, LIBRARY, t=t,
                      out=tmp_path, feature_names=["x"])
    with pytest.raises(ValueError, match=r"\{'a/b': .*\}\. Rename them, e\.g\. \['a_b_2'\]"):
        discover_many({"a/b": x, "a_b": x}, LIBRARY, t=t, out=tmp_path)  # a suggestion free
    with pytest.raises(ValueError, match=r"\[1, '1'\] would share one"):
        discover_many({1: x, "1": x}, LIBRARY, t=t, out=tmp_path)
    assert not (tmp_path / "runs.csv").exists()  # nothing ran, nothing written
    with pytest.raises(ValueError, match=r"seeds repeats \[0\]; .* pass each seed once"):
        discover_many([x], LIBRARY, t=t, seeds=[0, 1, 0])
    with pytest.raises(TypeError, match=r"seeds must be integers; got \[0\.5, 0\.7\]"):
        discover_many([x], LIBRARY, t=t, seeds=[0.5, 0.7])
    with pytest.raises(ValueError, match="max_time must be a number of seconds > 0"):
        discover_many([x], LIBRARY, t=t, max_time=0)  # once, not by every run


def test_the_table_says_why_a_run_is_not_confident(recordings):
    t, x = recordings["worm1"]
    (run,) = discover_many({"cut": x}, LIBRARY, t=t, max_time=1e-6, feature_names=["x"])
    assert not run.result.confident
    assert run.row()["doubts"] == "not checked; time budget"  # the budget cut it short


def test_a_batch_run_again_into_its_folder_adds_to_its_table(recordings, tmp_path):
    """A batch stopped and run again (or another batch) into the same folder keeps the
    rows written before; a file of another kind in the table's place is not written
    over; a result that cannot be written is its run's error, and the batch goes on."""
    t, x = recordings["worm1"]
    short = {"short": x[:6]}  # fails at once: a row without a result
    discover_many(short, LIBRARY, t=t[:6], out=tmp_path, feature_names=["x"])
    discover_many(short, LIBRARY, t=t[:6], out=tmp_path, feature_names=["x"])
    with open(tmp_path / "runs.csv") as fh:
        assert [r["name"] for r in csv.DictReader(fh)] == ["short", "short"]
    earlier = tmp_path / "earlier"  # a table written before the doubts column
    earlier.mkdir()
    (earlier / "runs.csv").write_text(",".join(c for c in COLUMNS if c != "doubts") + "\n")
    discover_many(short, LIBRARY, t=t[:6], out=earlier, feature_names=["x"])
    with open(earlier / "runs.csv") as fh:
        (row,) = list(csv.DictReader(fh))
    assert "doubts" not in row and row["name"] == "short" and row["error"]
    cut = tmp_path / "cut"  # a table whose last row lost its newline, saved with a BOM
    cut.mkdir()
    (cut / "runs.csv").write_bytes(b"\xef\xbb\xbf" + ",".join(COLUMNS).encode()
                                   + b"\nold,0,1.0,E,,,,,")
    discover_many(short, LIBRARY, t=t[:6], out=cut, feature_names=["x"])
    with open(cut / "runs.csv", encoding="utf-8-sig") as fh:
        assert [r["name"] for r in csv.DictReader(fh)] == ["old", "short"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "runs.csv").write_text("a,b\n1,2\n")
    with pytest.raises(ValueError, match=r"runs\.csv is not a table of runs \(its header is "
                       r"\['a', 'b'\].*give out= another folder"):
        discover_many(short, LIBRARY, t=t[:6], out=other, feature_names=["x"])
    assert (other / "runs.csv").read_text() == "a,b\n1,2\n"
    (tmp_path / "worm1.npz").mkdir()  # where its result would go: cannot be written
    run, failed = discover_many({"worm1": x, "short": x[:6]}, LIBRARY,
                                t={"worm1": t, "short": t[:6]}, out=tmp_path,
                                feature_names=["x"])
    assert run.result is not None and run.error.startswith(
        "result not saved (IsADirectoryError") and "run.result.save(path)" in run.error
    assert failed.error.startswith("ValueError")
    with open(tmp_path / "runs.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["name"] for r in rows] == ["short", "short", "worm1", "short"]
    assert rows[2]["error"].startswith("result not saved") and rows[2]["hidden_states"] == "1"
    assert not list(tmp_path.glob(".*.part"))  # no half-written file left beside


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
    with open(tmp_path / "out" / "runs.csv") as fh:
        assert sorted(r["name"] for r in csv.DictReader(fh)) == ["worm1", "worm2"]
    assert main(["discover", str(tmp_path / "*.nothing"), "--time", "t", "--observed", "x",
                 "--quiet"]) == 2
    assert "no data files" in capsys.readouterr().err
    one = str(folder / "worm1.csv")
    assert main(["discover", one, "--time", "t", "--observed", "x", "--scheduler",
                 "tcp://localhost:8786", "--quiet"]) == 2
    assert "leave --scheduler out" in capsys.readouterr().err
    assert main(["discover", one, "--time", "t", "--observed", "x", "--device", "tpu",
                 "--quiet"]) == 2
    assert "device must be 'cpu' or a CUDA device" in capsys.readouterr().err


def test_only_a_lone_run_may_use_a_second_process(monkeypatch):
    """Parallel workers have a core each: no helper process in them; a lone run
    (n_jobs=1) keeps the caller's setting, and the setting is restored after."""
    from latentsindy import _batch as batch
    from latentsindy._core import parallel

    seen = []
    monkeypatch.setattr(batch, "discover_hidden",
                        lambda *args, **kwargs: seen.append(parallel._enabled))
    batch._one("a", None, 1.0, None, 0, {}, alone=True)
    batch._one("a", None, 1.0, None, 0, {}, alone=False)
    assert parallel._enabled is True
    previous = parallel.enable(False)
    try:
        batch._one("a", None, 1.0, None, 0, {}, alone=True)  # switched off by the caller
        assert parallel._enabled is False
    finally:
        parallel.enable(previous)
    assert seen == [True, False, False]
