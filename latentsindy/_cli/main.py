"""The ``latentsindy`` command line: discover, show, simulate.

Results go to stdout or to files, progress to stderr. A problem with the input (a bad
file, a missing or non-numeric column, a bad option) is one line on stderr and exit
code 2; a discovery that cannot be done (no coefficient varies) exit code 1.
"""

from __future__ import annotations

import argparse
import csv
import glob
import re
import sys
from pathlib import Path

import numpy as np
import pysindy as ps

from .._batch import COLUMNS, discover_many
from .._core import validation as val
from .._files.load import load
from .._files.tables import DataError, read_columns
from .._stage_two.discover import discover_hidden

EXIT_USAGE = 2
EXIT_FAILED = 1


class UsageError(ValueError):
    """A command-line value that cannot be used (exit code 2)."""


def parse_library(spec: str):
    """A pysindy library from ``poly:DEGREE``, ``poly:DEGREE:nobias`` or ``fourier:N``."""
    parts = spec.split(":")
    try:
        kind, n = parts[0], int(parts[1])
        if kind == "poly" and len(parts) in (2, 3) and n >= 1:
            if len(parts) == 3 and parts[2] != "nobias":
                raise ValueError
            return ps.PolynomialLibrary(degree=n, include_bias=len(parts) == 2)
        if kind == "fourier" and len(parts) == 2 and n >= 1:
            return ps.FourierLibrary(n_frequencies=n)
        raise ValueError
    except (ValueError, IndexError):
        raise UsageError(f"library {spec!r} not understood; expected poly:DEGREE, "
                         "poly:DEGREE:nobias or fourier:N (for example poly:3).") from None


def _names(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise UsageError(f"expected comma-separated column names; got {text!r}.")
    return names


def _state_names(columns: list[str]) -> list[str]:
    """The observed columns' names as the equations' state names: a column that is no
    (ASCII) identifier, such as an array's column ``a:1`` or a dataset path ``run1/x``,
    is named with underscores (``a_1``, ``run1_x``), after any column already so named."""
    valid = [c.isascii() and c.isidentifier() for c in columns]
    taken = {c for c, ok in zip(columns, valid, strict=True) if ok}
    names = []
    for column, ok in zip(columns, valid, strict=True):
        if ok:
            names.append(column)
            continue
        name = re.sub(r"[^0-9A-Za-z_]", "_", column)
        name = f"x_{name}" if not name or name[0].isdigit() else name
        while name in taken:
            name += "_"
        taken.add(name)
        names.append(name)
    return names


SUFFIXES = (".csv", ".npz", ".h5", ".hdf5")


def _data_files(spec: str) -> tuple[list[Path], bool]:
    """The files named by DATA (a file, a folder or a glob) and whether it is a batch."""
    path = Path(spec)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in SUFFIXES)
    elif any(ch in spec for ch in "*?["):
        files = sorted(Path(p) for p in glob.glob(spec) if Path(p).is_file())
    else:
        return [path], False
    if not files:
        raise UsageError(f"{spec}: no data files ({', '.join(SUFFIXES)}) found there.")
    return files, True


def _series(path, args, observed):
    columns = read_columns(path, [args.time, *observed], missing=observed)
    t = columns[args.time]
    if len(t) < 10 or np.any(np.diff(t) <= 0):
        raise UsageError(f"{path}: time column {args.time!r} must increase strictly "
                         f"over at least 10 rows; got {len(t)} rows.")
    return t, np.column_stack([columns[n] for n in observed])


def _discover(args) -> int:
    observed = _names(args.observed)
    library = parse_library(args.library)
    closure = parse_library(args.closure_library) if args.closure_library else None
    hidden_names = _names(args.hidden_names) if args.hidden_names else None
    files, batch = _data_files(args.data)
    try:
        val.check_device(args.device)
        args.max_time = val.check_seconds(args.max_time, "--max-time")
    except ValueError as err:
        raise UsageError(str(err)) from None
    if args.scheduler and not batch:
        raise UsageError("--scheduler runs a folder or glob of data files on a Dask cluster; "
                         f"{args.data} is one file: leave --scheduler out.")
    if batch:
        return _discover_batch(args, files, observed, library, closure, hidden_names)
    t, x = _series(files[0], args, observed)
    _progress(args, f"discovering hidden states from {len(observed)} observed column(s), "
                    f"{len(t)} samples ...")
    result = discover_hidden(x, library, t=t, feature_names=_named(args, observed),
                             hidden_names=hidden_names, closure_library=closure,
                             generator=args.generator, refine=not args.no_refine,
                             gaps=args.gaps, outliers=args.outliers, max_hidden=args.max_hidden,
                             max_time=args.max_time,
                             device=args.device,
                             seed=args.seed,
                             verbose=not args.quiet)
    print(result.summary())
    if args.out:
        result.save(args.out)
        _progress(args, f"result written to {args.out}")
    if args.plot:
        result.plot(path=args.plot)
        _progress(args, f"figure written to {args.plot}")
    return 0


def _discover_batch(args, files, observed, library, closure, hidden_names) -> int:
    names = [p.stem for p in files]
    if len(set(names)) != len(names):
        raise UsageError("data files must have distinct names (without suffix); got "
                         f"{[p.name for p in files]}.")
    data = {p.stem: _series(p, args, observed) for p in files}
    where = (f"on the Dask scheduler at {args.scheduler}" if args.scheduler else
             f"with {args.jobs} worker(s)")
    _progress(args, f"discovering hidden states in {len(files)} files {where} ...")
    runs = discover_many({k: x for k, (_, x) in data.items()}, library,
                         t={k: t for k, (t, _) in data.items()}, n_jobs=args.jobs,
                         backend=args.backend, scheduler=args.scheduler, out=args.out,
                         feature_names=_named(args, observed),
                         hidden_names=hidden_names, closure_library=closure,
                         generator=args.generator, refine=not args.no_refine,
                         gaps=args.gaps, outliers=args.outliers, max_hidden=args.max_hidden,
                         max_time=args.max_time,
                         device=args.device,
                         seeds=[args.seed])
    if args.out:
        _progress(args, f"results and runs.csv written to {Path(args.out)}/ as they finished")
    writer = csv.DictWriter(sys.stdout, fieldnames=COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows(r.row() for r in runs)
    return 0 if all(r.error is None for r in runs) else EXIT_FAILED


def _load(path):
    if not Path(path).is_file():
        raise DataError(f"{path}: no such file.")
    return load(path)


def _show(args) -> int:
    result = _load(args.result)
    print(result.to_latex() if args.latex else result.summary())
    return 0


def _simulate(args) -> int:
    result = _load(args.result)
    t = result.times
    if args.n_times is not None and args.n_times < 2:
        raise UsageError(f"--n-times must be at least 2; got {args.n_times}.")
    if args.t_end is not None and not args.t_end > t[0]:
        raise UsageError(f"--t-end must be after the first time {t[0]:g}; got {args.t_end:g}.")
    if args.max_steps < 1:
        raise UsageError(f"--max-steps must be positive; got {args.max_steps}.")
    if args.t_end is not None or args.n_times is not None:
        t = np.linspace(t[0], args.t_end if args.t_end is not None else t[-1],
                        args.n_times if args.n_times is not None else len(t))
    sim = result.simulate(t, max_steps=args.max_steps)
    _progress(args, f"simulation: {sim.status}; {sim.message}")
    table = np.column_stack([sim.t, sim.x])
    header = ",".join(("t", *sim.state_names))
    if args.out:
        np.savetxt(args.out, table, delimiter=",", header=header, comments="")
        _progress(args, f"trajectory written to {args.out}")
    else:
        np.savetxt(sys.stdout, table, delimiter=",", header=header, comments="")
    return 0 if sim.status == "success" else EXIT_FAILED


def _named(args, observed):
    """:func:`_state_names` of the observed columns, saying which were renamed."""
    names = _state_names(observed)
    renamed = [f"{c} as {n}" for c, n in zip(observed, names, strict=True) if c != n]
    if renamed:
        _progress(args, f"columns named in the equations: {', '.join(renamed)}")
    return names


def _progress(args, text):
    if not getattr(args, "quiet", False):
        print(text, file=sys.stderr)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="latentsindy",
        description="Discover hidden variables and a closed ODE from partial observations.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    d = sub.add_parser("discover", help="infer hidden states and a closed ODE from data",
                       description="Infer hidden states and a closed, autonomous ODE from "
                                   "observed columns of a CSV, NPZ or HDF5 file.")
    d.add_argument("data", help="CSV (header row of names), NPZ or HDF5 file; a folder or "
                                "a glob (quoted) runs every file and prints one table")
    d.add_argument("--time", required=True, help="name of the time column")
    d.add_argument("--observed", required=True, help="observed columns, comma-separated")
    d.add_argument("--library", default="poly:2",
                   help="candidate terms: poly:DEGREE[:nobias] or fourier:N (default poly:2)")
    d.add_argument("--closure-library", help="candidates of the hidden equations "
                                             "(default poly:2)")
    d.add_argument("--hidden-names", help="names of the hidden states, comma-separated")
    d.add_argument("--generator", choices=("timevae", "hypersindy"), default="timevae")
    d.add_argument("--no-refine", action="store_true",
                   help="skip refinement by integration (faster, nothing is checked)")
    d.add_argument("--gaps", choices=("split", "raise"), default="split",
                   help="missing values (empty fields, nan) in observed columns and long "
                        "time steps split a recording into segments (default) or are refused")
    d.add_argument("--outliers", choices=("discount", "keep"), default="discount",
                   help="isolated spikes (one sample far off its neighbours' curve) are "
                        "replaced by that curve and listed (default) or kept as measured")
    d.add_argument("--max-hidden", type=int, default=3,
                   help="at most this many hidden states in any structure (default 3)")
    d.add_argument("--max-time", type=float, default=None, metavar="SECONDS",
                   help="wall seconds per call: once spent, the best system found so far "
                        "is returned with a 'time budget' doubt (default: no limit)")
    d.add_argument("--device", default="cpu",
                   help="torch device for stage one and the refinement (cpu, cuda, cuda:1)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--out", help="write the result here (.npz; read with latentsindy show); "
                               "for a folder or glob: a folder of results and runs.csv, "
                               "each written as it finishes")
    d.add_argument("--jobs", type=int, default=1,
                   help="parallel workers for a folder or glob (-1: one per core)")
    d.add_argument("--backend", help="joblib backend for the workers (default local "
                                     "processes; dask or ray once registered with joblib)")
    d.add_argument("--scheduler", help="for a folder or glob: run on this Dask scheduler "
                                       "(tcp://host:8786; needs latentsindy[cluster])")
    d.add_argument("--plot", help="write a figure here (.png, .pdf, ...; needs matplotlib)")
    d.add_argument("--quiet", action="store_true", help="no progress on stderr")
    d.set_defaults(run=_discover)

    s = sub.add_parser("show", help="print a saved result",
                       description="Print a saved result's summary (or LaTeX).")
    s.add_argument("result", help="a result file written by discover --out")
    s.add_argument("--latex", action="store_true", help="the equations as LaTeX")
    s.set_defaults(run=_show)

    m = sub.add_parser("simulate", help="integrate a saved closed system",
                       description="Integrate a saved result's closed system from its "
                                   "fitted initial state; CSV (t and every state) to "
                                   "stdout or --out.")
    m.add_argument("result", help="a result file written by discover --out")
    m.add_argument("--t-end", type=float, help="end time (default: the data's)")
    m.add_argument("--n-times", type=int, help="number of output times (default: the data's)")
    m.add_argument("--max-steps", type=int, default=20_000,
                   help="integrator step budget (default 20000); exit code 1 when exhausted")
    m.add_argument("--out", help="write the trajectory here (CSV)")
    m.add_argument("--quiet", action="store_true", help="no progress on stderr")
    m.set_defaults(run=_simulate)
    return parser


def main(argv=None) -> int:
    """Run the command line; returns the exit code."""
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (DataError, UsageError) as err:
        print(f"latentsindy {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except ValueError as err:  # the library's own errors say what to do
        print(f"latentsindy {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE if args.command != "discover" else EXIT_FAILED
    except ImportError as err:
        print(f"latentsindy {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
