"""The benchmarks' runner keeps every finished row on disk, so a run cut short (a session
ending, a worker dying) keeps what it measured."""

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _runner import run_all  # noqa: E402


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
