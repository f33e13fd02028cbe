"""The benchmarks' runner keeps every finished row on disk, so a run cut short (a session
ending, a worker dying) keeps what it measured."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _runner import environment, run_all  # noqa: E402


def test_environment_names_the_versions_and_blas_a_table_depends_on():
    """A table's borderline calls can move with numpy's or scipy's OpenBLAS build, so
    every run prints the versions, the BLAS kernels and the CPU it ran on."""
    import numpy
    import scipy

    line = environment()
    assert line.startswith("environment: Python ")
    assert f"numpy {numpy.__version__}," in line and f"scipy {scipy.__version__}," in line
    assert "BLAS " in line
    assert "CPU " in line


def test_rows_are_written_as_they_finish(tmp_path):
    out = tmp_path / "rows.json"
    on_disk = []

    def report(row):
        on_disk.append(json.loads(out.read_text()) if out.exists() else None)

    def crash_on_third(k):
        if k == 2:
            raise RuntimeError("the run is cut short")
        return {"case": k, "value": k / 4}

    with pytest.raises(RuntimeError, match="cut short"):
        run_all(crash_on_third, [(0,), (1,), (2,)], report, jobs=1, out=out)
    assert on_disk == [None, [{"case": 0, "value": 0.0}]]
    assert json.loads(out.read_text()) == [{"case": 0, "value": 0.0}, {"case": 1, "value": 0.25}]


def _threads(_):
    import torch
    from threadpoolctl import threadpool_info

    return {"torch": torch.get_num_threads(),
            "blas": [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]}


def test_worker_processes_run_torch_and_the_blas_on_one_thread():
    """Workers of ``jobs > 1`` use one thread for torch and for the BLAS (numpy is
    imported before the workers fork: an environment variable set then comes too late,
    and two BLAS threads per worker oversubscribed the cores)."""
    rows = run_all(_threads, [(0,), (1,)], lambda row: None, jobs=2)
    assert all(r["torch"] == 1 and r["blas"] and set(r["blas"]) == {1} for r in rows)
