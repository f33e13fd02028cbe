"""The command line: the same result as the Python call, every --help, and one clear
line with exit code 2 for every input problem."""

import subprocess
import sys

import numpy as np
import pytest

from latentsindy import load
from latentsindy._cli.main import main
from latentsindy._files.tables import DataError, read_columns


@pytest.fixture(scope="module")
def lv_csv(lv, tmp_path_factory):
    data, _ = lv
    path = tmp_path_factory.mktemp("cli") / "prey.csv"
    np.savetxt(path, np.column_stack([data.t, data.x[:, 0], data.x_clean[:, 1]]),
               delimiter=",", header="t,x,predator", comments="")
    return path


def test_discover_gives_the_python_result_and_show_and_simulate_read_it(lv, lv_csv,
                                                                       tmp_path, capsys):
    """The CSV of conftest's LV series through the command line gives the equations of
    the Python call with the same options; show prints the same summary, simulate the
    closed system's trajectory."""
    _, expected = lv
    out = tmp_path / "result.npz"
    code = main(["discover", str(lv_csv), "--time", "t", "--observed", "x",
                 "--library", "poly:3:nobias", "--hidden-names", "h", "--out", str(out),
                 "--quiet"])
    printed = capsys.readouterr()
    assert code == 0 and printed.err == ""
    result = load(out)
    assert result.summary() == printed.out.rstrip("\n")
    assert [(t.state, t.feature) for t in result.terms] == \
        [(t.state, t.feature) for t in expected.terms]
    np.testing.assert_allclose([t.value for t in result.terms],
                               [t.value for t in expected.terms], rtol=1e-8)

    assert main(["show", str(out)]) == 0
    assert capsys.readouterr().out.rstrip("\n") == result.summary()
    assert main(["show", str(out), "--latex"]) == 0
    assert capsys.readouterr().out.rstrip("\n") == result.to_latex()

    assert main(["simulate", str(out), "--n-times", "50", "--quiet"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "t,x,h" and len(lines) == 51
    table = np.loadtxt(lines[1:], delimiter=",")
    np.testing.assert_allclose(table[0, 1:], result.initial_state)
    assert main(["simulate", str(out), "--n-times", "0", "--quiet"]) == 2
    assert "--n-times must be at least 2; got 0" in capsys.readouterr().err
    assert main(["simulate", str(out), "--t-end", "1e6", "--n-times", "5", "--max-steps",
                 "100", "--quiet", "--out", str(tmp_path / "far.csv")]) == 1


@pytest.mark.parametrize("command", [[], ["discover"], ["show"], ["simulate"]])
def test_every_command_has_help(command, capsys):
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--help"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.startswith("usage: latentsindy")


def test_module_entry_point_runs():
    done = subprocess.run([sys.executable, "-m", "latentsindy", "show", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "usage: latentsindy show" in done.stdout


def _one_line_error(capsys, code, message):
    err = capsys.readouterr().err
    assert code == 2, err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert message in err


def test_input_problems_are_one_line_and_exit_code_2(lv_csv, tmp_path, capsys):
    base = ["discover", "--time", "t", "--observed", "x", "--quiet"]
    _one_line_error(capsys, main([base[0], str(tmp_path / "none.csv"), *base[1:]]),
                    "none.csv: no such file.")
    _one_line_error(capsys, main([base[0], str(lv_csv), "--time", "t", "--observed",
                                  "y", "--quiet"]), "no column 'y'; columns are")
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x\n0,1\n1,oops\n")
    _one_line_error(capsys, main([base[0], str(bad), *base[1:]]),
                    "column 'x' is not numeric: 'oops' in data row 2")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file")
    _one_line_error(capsys, main([base[0], str(garbage), *base[1:]]),
                    "cannot be read as NPZ")
    _one_line_error(capsys, main([*base[:1], str(lv_csv), *base[1:], "--library", "cubic"]),
                    "library 'cubic' not understood")
    _one_line_error(capsys, main([*base[:1], str(lv_csv), *base[1:], "--max-time", "0"]),
                    "--max-time must be a number of seconds > 0 (leave it out for no limit); "
                    "got 0.0")
    _one_line_error(capsys, main(["show", str(garbage)]), "not a latentsindy file")
    _one_line_error(capsys, main(["show", str(lv_csv)]), "not a latentsindy file")


def test_columns_from_npz_and_hdf5(tmp_path):
    """1-D arrays by name, a 2-D array's columns as name:j, HDF5 groups as paths."""
    import h5py

    t, xy = np.linspace(0, 1, 5), np.arange(10.0).reshape(5, 2)
    np.savez(tmp_path / "d.npz", t=t, xy=xy)
    cols = read_columns(tmp_path / "d.npz", ["t", "xy:1"])
    np.testing.assert_array_equal(cols["xy:1"], xy[:, 1])
    with h5py.File(tmp_path / "d.h5", "w") as fh:
        fh["run/t"] = t
        fh["run/x"] = xy[:, 0]
        fh["run/label"] = np.array([b"a"] * 5)
    cols = read_columns(tmp_path / "d.h5", ["run/t", "run/x"])
    np.testing.assert_array_equal(cols["run/x"], xy[:, 0])
    with pytest.raises(DataError, match="'run/label' must be a 1-D numeric array"):
        read_columns(tmp_path / "d.h5", ["run/label"])
    with pytest.raises(DataError, match="unknown format '.txt'"):
        (tmp_path / "d.txt").write_text("1")
        read_columns(tmp_path / "d.txt", ["t"])


def test_array_columns_and_dataset_paths_become_state_names(tmp_path, capsys, monkeypatch):
    """An observed column that is no identifier (``xy:1``, ``run/x``) is named with
    underscores in the equations, and the progress says so."""
    from latentsindy._cli import main as cli

    assert cli._state_names(["xy:1", "run1/x", "x", "1st", "a-b", "a_b", "x\u00b2"]) == \
        ["xy_1", "run1_x", "x", "x_1st", "a_b_", "a_b", "x_"]
    seen = {}

    def fake(x, library, *, t, feature_names, **kw):
        seen["names"], seen["shape"] = feature_names, x.shape
        raise SystemExit(0)

    monkeypatch.setattr(cli, "discover_hidden", fake)
    t, xy = np.linspace(0, 1, 50), np.arange(100.0).reshape(50, 2)
    np.savez(tmp_path / "d.npz", t=t, xy=xy)
    with pytest.raises(SystemExit):
        main(["discover", str(tmp_path / "d.npz"), "--time", "t", "--observed", "xy:0,xy:1"])
    assert seen == {"names": ["xy_0", "xy_1"], "shape": (50, 2)}
    assert "columns named in the equations: xy:0 as xy_0, xy:1 as xy_1" in capsys.readouterr().err


def test_missing_observed_values_are_gaps_and_can_be_refused(tmp_path, capsys):
    """Empty fields in an observed column are read as missing samples (split into
    segments by default); --gaps raise refuses them; a missing time is a data error."""
    from latentsindy._files.tables import read_columns

    path = tmp_path / "holes.csv"
    rows = ["t,x"] + [f"{0.1 * k:.1f},{'' if k == 20 else np.sin(0.1 * k):}" for k in range(60)]
    path.write_text("\n".join(rows) + "\n")
    columns = read_columns(path, ["t", "x"], missing=["x"])
    assert np.isnan(columns["x"][20]) and np.isfinite(np.delete(columns["x"], 20)).all()
    code = main(["discover", str(path), "--time", "t", "--observed", "x", "--gaps", "raise",
                 "--quiet"])
    err = capsys.readouterr().err
    assert code == 1 and "1 row(s) with a NaN value or time (first at row 20)" in err
    path.write_text("t,x\n0,1\n,2\n2,3\n")
    _one_line_error(capsys, main(["discover", str(path), "--time", "t", "--observed", "x",
                                  "--quiet"]), "column 't' has a missing or infinite value")
