"""Discovery over many recordings (or seeds) in parallel, collected in one table.

Runs go through joblib: local processes by default; any joblib backend the user names
(``"dask"`` or ``"ray"`` once their joblib integration is registered, see joblib's
``parallel_config``) spreads them over a cluster. Each worker runs torch on one thread,
so ``n_jobs`` workers use ``n_jobs`` cores. A run that fails is recorded with its error
message; the others go on.
"""

from __future__ import annotations

import csv
import time
from dataclasses import dataclass

import numpy as np
import torch
from joblib import Parallel, delayed

from .._stage_two.discover import discover_hidden


@dataclass(frozen=True)
class Run:
    """One discovery of a batch: its name, seed, result (None if it failed), error
    message (None if it succeeded) and wall time in seconds."""

    name: str
    seed: int
    result: object
    error: str | None
    wall: float

    def row(self) -> dict:
        """The run as one table row."""
        r = self.result
        row = {"name": self.name, "seed": self.seed, "wall_s": round(self.wall, 2),
               "error": self.error or ""}
        if r is None:
            return row | {"hidden_states": "", "confident": "", "score": "", "equations": ""}
        return row | {
            "hidden_states": len(r.hidden_names), "confident": r.confident,
            "score": float(r.score),
            "equations": "; ".join(f"d{n}/dt = {e}" for n, e in r.rhs.items()),
        }


def _one(name, x, t, library, seed, options):
    torch.set_num_threads(1)
    start = time.perf_counter()
    try:
        result = discover_hidden(x, library, t=t, seed=seed, verbose=False, **options)
        return Run(name, seed, result, None, time.perf_counter() - start)
    except Exception as err:  # noqa: BLE001 - a failed run is recorded, the batch goes on
        return Run(name, seed, None, f"{type(err).__name__}: {err}",
                   time.perf_counter() - start)


def discover_many(recordings, library=None, *, t, seeds=(0,), n_jobs=1, backend=None,
                  **options) -> list[Run]:
    """Run :func:`discover_hidden` on every recording and seed, in parallel.

    Parameters
    ----------
    recordings : dict {name: array (n_times, n_observed)} or list of arrays
        The observed series (a list is named ``0, 1, ...``).
    library : pysindy feature library, optional
    t : float, array, or dict {name: float or array}
        Sample spacing or times, shared or per recording.
    seeds : sequence of int
        Every recording is run once per seed.
    n_jobs : int
        Parallel workers (joblib; -1: one per core).
    backend : str, optional
        A joblib backend (default: joblib's local processes, "loky").
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
    seeds = [int(s) for s in np.atleast_1d(seeds)]
    for key in ("seed", "verbose"):
        if key in options:
            raise TypeError(f"discover_many sets {key!r} itself; use seeds=[...] instead."
                            if key == "seed" else "discover_many runs quietly (verbose=False).")
    jobs = [delayed(_one)(name, x, times[name], library, seed, options)
            for name, x in recordings.items() for seed in seeds]
    return list(Parallel(n_jobs=n_jobs, backend=backend)(jobs))


def write_table(runs, path) -> None:
    """Write ``[r.row() for r in runs]`` as CSV."""
    rows = [r.row() for r in runs]
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
