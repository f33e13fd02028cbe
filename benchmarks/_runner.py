"""Running benchmark cases, one after another or in processes of one torch thread."""

from __future__ import annotations

import json
import os
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from pathlib import Path

# the packages whose versions a table's numbers depend on (their BLAS builds included)
PACKAGES = ("latentsindy", "numpy", "scipy", "numba", "llvmlite", "torch", "pysindy",
            "scikit-learn")


def environment() -> str:
    """One line naming what a table's numbers depend on besides the commit: Python, the
    packages' versions, the BLAS libraries loaded and the kernels they chose, the CPU.
    A discovery turns on near-ties, so a borderline call can end differently under other
    builds of numpy or scipy (their OpenBLAS) or on another CPU: compare tables made in
    one environment."""
    import platform
    from importlib import metadata

    import scipy.linalg  # noqa: F401 - loads scipy's own BLAS beside numpy's
    from threadpoolctl import threadpool_info

    versions = []
    for name in PACKAGES:
        try:
            versions.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            versions.append(f"{name} absent")
    blas = sorted({f"{i['internal_api']} {i['version']} ({i.get('architecture') or '?'})"
                   for i in threadpool_info() if i.get("user_api") == "blas"})
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next(line.split(":", 1)[1].strip() for line in fh
                       if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return (f"environment: Python {platform.python_version()}, {', '.join(versions)}; "
            f"BLAS {'; '.join(blas) or 'unknown'}; CPU {cpu}, {os.cpu_count()} cores")


def _single_threaded():
    import torch
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    # the BLAS too: the parent imported numpy before OMP_NUM_THREADS was set, so each
    # forked worker would run two BLAS threads on its one core (stage two's timings
    # were 2-9x a lone call's, and varied from run to run)
    threadpool_limits(1)
    # and no second process per call (latentsindy._core.parallel): each worker has a core
    from latentsindy._core import parallel

    parallel.enable(False)


def _call(run, task):
    return run(*task)


def run_all(run, tasks, report, jobs=1, out=None):
    """``run(*task)`` for every task, each row passed to ``report`` as it comes (in task
    order), in ``jobs`` processes of one thread each (wall times then include
    contention); the rows so far written as JSON to ``out`` after every row when given
    (a run cut short keeps what it measured). Returns the rows."""
    rows = []

    def keep(row):
        rows.append(row)
        report(row)
        if out:  # written beside, then moved: a kill mid-write leaves the last good file
            part = Path(f"{out}.part")
            part.write_text(json.dumps(rows, indent=1, default=float))
            os.replace(part, out)

    if jobs > 1:
        os.environ.setdefault("OMP_NUM_THREADS", "1")
        with ProcessPoolExecutor(jobs, initializer=_single_threaded) as pool:
            for row in pool.map(partial(_call, run), tasks):
                keep(row)
    else:
        for task in tasks:
            keep(run(*task))
    return rows
