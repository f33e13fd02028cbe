"""Discovery over many recordings (or seeds) in parallel, collected in one table.

Runs go through joblib's local processes by default (``n_jobs`` workers, or any joblib
backend by name), or to a Dask cluster (``scheduler=``: a scheduler's address or a
``distributed.Client``), where they are submitted as futures and collected as they
finish. Each worker runs torch on one thread, so ``n_jobs`` workers use ``n_jobs``
cores. A run that fails, or whose worker dies, is recorded with its error message; the
others go on. With ``out=`` every run is written the moment it finishes (its result
file and its row of ``runs.csv``), so a batch that is stopped keeps what it finished.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from joblib import Parallel, delayed

from ._core import parallel
from ._core import validation as val
from ._stage_two.discover import discover_hidden
from ._stage_two.result import HiddenDiscovery

TABLE = "runs.csv"
COLUMNS = ("name", "seed", "wall_s", "error", "hidden_states", "confident", "score",
           "doubts", "equations")
# the table's columns before "doubts" was added: such a table is added to as it is
_EARLIER = tuple(c for c in COLUMNS if c != "doubts")


@dataclass(frozen=True)
class Run:
    """One discovery of a batch: its name, seed, result (None if it failed), error
    message (None if it succeeded; with ``out=``, also set where its result could not be
    written) and wall time in seconds."""

    name: str
    seed: int
    result: HiddenDiscovery | None
    error: str | None
    wall: float

    def row(self) -> dict:
        """The run as one table row."""
        r = self.result
        row = {"name": self.name, "seed": self.seed,
               "wall_s": "" if math.isnan(self.wall) else round(self.wall, 2),
               "error": self.error or ""}
        if r is None:
            return row | {"hidden_states": "", "confident": "", "score": "", "doubts": "",
                          "equations": ""}
        return row | {
            "hidden_states": len(r.hidden_names), "confident": r.confident,
            "score": float(r.score),
            # why a result is not confident, by kind (the sentences are in its file)
            "doubts": "; ".join([*dict.fromkeys(d.kind for d in r.doubts)]
                                + ["structure uncertain"] * bool(r.uncertain)),
            "equations": "; ".join(f"d{n}/dt = {e}" for n, e in r.rhs.items()),
        }


def _one(name, x, t, library, seed, options, alone=False) -> Run:
    """One discovery on one torch thread (restored after: n_jobs=1 runs in-process);
    with a second process for its independent pieces only when it runs ``alone``
    (:mod:`latentsindy._core.parallel`): parallel workers have a core each."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    helpers = parallel.enable(False)
    parallel.enable(helpers and alone)  # never on where the caller switched it off
    start = time.perf_counter()
    try:
        result = discover_hidden(x, library, t=t, seed=seed, verbose=False, **options)
        return Run(name, seed, result, None, time.perf_counter() - start)
    except Exception as err:  # noqa: BLE001 - a failed run is recorded, the batch goes on
        return Run(name, seed, None, f"{type(err).__name__}: {err}",
                   time.perf_counter() - start)
    finally:
        torch.set_num_threads(threads)
        parallel.enable(helpers)


def discover_many(recordings, library=None, *, t, seeds=(0,), n_jobs=1, backend=None,
                  scheduler=None, out=None, **options) -> list[Run]:
    """Run :func:`discover_hidden` on every recording and seed, in parallel.

    Parameters
    ----------
    recordings : dict {name: array (n_times, n_observed)} or list of arrays
        The observed series (a list is named ``0, 1, ...``).
    library : pysindy feature library, optional
    t : float, array, or dict {name: float or array}
        Sample spacing or times, shared or per recording.
    seeds : sequence of int
        Every recording is run once per seed (each seed once).
    n_jobs : int
        Parallel local workers (joblib; -1: one per core).
    backend : str, optional
        A joblib backend (default: joblib's local processes, "loky").
    scheduler : str or distributed.Client, optional
        Run on a Dask cluster instead: the scheduler's address (``"tcp://host:8786"``)
        or a connected client (``pip install "latentsindy[cluster]"``). A run whose
        worker dies is recorded as failed (``KilledWorker``) once Dask gives up on it.
    out : path, optional
        A folder: every run is written as it finishes, its result as ``NAME.npz``
        (``NAME_seedS.npz`` with several seeds; a name with a path separator is refused)
        and its row appended to ``runs.csv`` (a table already there is kept and added
        to: run again into the same folder, the new rows follow the old, and results of
        the same name are written over). A result that cannot be written is that run's
        error (the result is still in ``run.result``); the batch goes on.
    **options
        Passed to :func:`discover_hidden` (``feature_names``, ``closure_library``, ...).

    Returns
    -------
    list of Run, in the order of recordings and then seeds. ``[r.row() for r in runs]``
    is one table.
    """
    if not isinstance(recordings, dict):
        recordings = {str(k): x for k, x in enumerate(recordings)}
    if not recordings:
        raise ValueError("recordings is empty; pass a dict {name: array} or a list of arrays.")
    times = t if isinstance(t, dict) else dict.fromkeys(recordings, t)
    missing = sorted(set(recordings) - set(times))
    if missing:
        raise ValueError(f"t has no entry for recording(s) {missing}.")
    given = np.atleast_1d(seeds)
    if given.dtype.kind not in "iu":
        raise TypeError(f"seeds must be integers; got {given.tolist()!r}. Pass e.g. "
                        "seeds=[0, 1].")
    seeds = [int(s) for s in given]
    repeated = sorted({s for s in seeds if seeds.count(s) > 1})
    if repeated:
        raise ValueError(f"seeds repeats {repeated}; a seed gives the same run every time, "
                         "so pass each seed once.")
    if out is not None:
        _check_file_names(recordings)
    if "max_time" in options:  # refused once, here, rather than by every run
        options = options | {"max_time": val.check_seconds(options["max_time"], "max_time")}
    for key in ("seed", "verbose"):
        if key in options:
            raise TypeError(f"discover_many sets {key!r} itself; use seeds=[...] instead."
                            if key == "seed" else "discover_many runs quietly (verbose=False).")
    if scheduler is not None and backend is not None:
        raise ValueError(f"give scheduler= (a Dask cluster) or backend= (joblib), not both; "
                         f"got scheduler={scheduler!r} and backend={backend!r}.")
    if scheduler is None and "device" in options:
        options = options | {"device": val.check_device(options["device"])}
    calls = [(name, x, times[name], library, seed, options)
             for name, x in recordings.items() for seed in seeds]
    write = _Writer(out, several_seeds=len(seeds) > 1) if out is not None else None
    finished = {}
    runs = (_on_dask(scheduler, calls) if scheduler is not None else
            Parallel(n_jobs=n_jobs, backend=backend, return_as="generator_unordered")(
                delayed(_one)(*call, alone=n_jobs == 1) for call in calls))
    for run in runs:
        if write is not None:
            run = write(run)
        finished[run.name, run.seed] = run
    return [finished[name, seed] for name, _, _, _, seed, _ in calls]


_RESERVED = {"CON", "PRN", "AUX", "NUL", *(f"{p}{k}" for p in ("COM", "LPT") for k in range(1, 10))}
_NOT_IN_NAMES = '/\\:*?"<>|'  # path separators and what Windows refuses in a file name


def _file_name_fault(name: str) -> str | None:
    """Why ``name`` cannot be a result's file name on every system; None if it can."""
    if name.strip(" .") == "":
        return "no name"
    if any(c in _NOT_IN_NAMES or ord(c) < 32 for c in name):
        return "a path separator, or a character Windows refuses"
    if name.split(".")[0].upper() in _RESERVED or name[-1] in " .":
        return "a name Windows reserves, or one ending in a space or dot"
    return None


def _check_file_names(recordings) -> None:
    """With ``out=``, each recording's name is its result's file name: refuse names that
    cannot be one on every system, and names that would share a file (``1`` and
    ``"1"``; ``A`` and ``a`` on a case-insensitive disk), before any run starts."""
    names = [str(name) for name in recordings]
    faults = {n: f for n in names if (f := _file_name_fault(n)) is not None}
    if faults:
        taken = {n.lower() for n in names if n not in faults}
        fixed = []
        for n in faults:
            base = "".join("_" if c in _NOT_IN_NAMES or ord(c) < 32 else c
                           for c in n).strip(" .") or "run"
            if _file_name_fault(base):  # what is left is a reserved name
                base = f"{base}_"
            candidate, k = base, 1
            while candidate.lower() in taken:
                k += 1
                candidate = f"{base}_{k}"
            taken.add(candidate.lower())
            fixed.append(candidate)
        raise ValueError(f"with out=, each recording's name names its result file; these "
                         f"cannot: {faults}. Rename them, e.g. {fixed}.")
    lowered = [n.lower() for n in names]
    shared = [name for name, low in zip(recordings, lowered, strict=True)
              if lowered.count(low) > 1]
    if shared:
        raise ValueError(f"with out=, each recording's name names its result file; {shared} "
                         "would share one (names are compared as text, ignoring case): "
                         "rename them apart.")


def _on_dask(scheduler, calls):
    """Runs on a Dask cluster, yielded as they finish."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise ImportError("scheduler= runs on a Dask cluster and needs dask.distributed: "
                          'pip install "latentsindy[cluster]".') from None
    client = scheduler if isinstance(scheduler, Client) else Client(scheduler)
    try:
        futures = {client.submit(_one, *call, pure=False): call for call in calls}
        for future in as_completed(futures):
            name, seed = futures[future][0], futures[future][4]
            try:
                run = future.result()
            except Exception as err:  # noqa: BLE001 - the worker died or the task was lost
                run = Run(name, seed, None, f"{type(err).__name__}: {err}", math.nan)
            future.release()
            yield run
    finally:
        if client is not scheduler:
            client.close()


class _Writer:
    """Writes each run as it finishes: its result file and its row of ``runs.csv``
    (appended to the folder's table where it has one: a batch run again into the same
    folder keeps the rows before it, and writes its results over those of the same
    name)."""

    def __init__(self, out, several_seeds: bool):
        self.folder = Path(out)
        self.folder.mkdir(parents=True, exist_ok=True)
        self.several_seeds = several_seeds
        table = self.folder / TABLE
        self.columns: tuple[str, ...] = COLUMNS
        if table.exists() and table.stat().st_size:
            with open(table, newline="", encoding="utf-8-sig") as fh:  # a spreadsheet's BOM
                header = tuple(next(csv.reader(fh), []))
            if header not in (COLUMNS, _EARLIER):
                raise ValueError(f"{table} is not a table of runs (its header is "
                                 f"{list(header)}, expected {list(COLUMNS)}); give out= "
                                 "another folder, or move that file.")
            self.columns = header  # an earlier table: its columns
            with open(table, "rb+") as fh:  # a last row cut short of its newline: end it
                fh.seek(-1, 2)
                if fh.read(1) != b"\n":
                    fh.write(b"\n")
            return
        with open(table, "w", newline="") as fh:
            csv.DictWriter(fh, fieldnames=COLUMNS).writeheader()

    def path(self, run: Run) -> Path:
        stem = f"{run.name}_seed{run.seed}" if self.several_seeds else run.name
        return self.folder / f"{stem}.npz"

    def __call__(self, run: Run) -> Run:
        """Write ``run``; returns it, with the error where its result could not be
        written (the batch goes on)."""
        if run.result is not None:
            try:
                run.result.save(self.path(run))
            except Exception as err:  # noqa: BLE001 - the run stands; the batch goes on
                run = dataclasses.replace(run, error=(
                    f"result not saved ({type(err).__name__}: {err}); it is in run.result: "
                    "save it elsewhere with run.result.save(path)"))
        with open(self.folder / TABLE, "a", newline="") as fh:
            csv.DictWriter(fh, fieldnames=self.columns,
                           extrasaction="ignore").writerow(run.row())
        return run

