"""Stage-one benchmark: wall time, peak memory, parameter count and accuracy.

Fits DynamicSINDy at default settings on the oscillator (switching A(t), 1% noise)
and on prey-only Lotka-Volterra (1% noise) at T = 1000, 2000 and 8000 samples, one
trajectory each, and prints a Markdown table. Peak memory is the resident-set growth
of a fresh process per run (so runs do not hide each other's peaks).

Usage::

    python benchmarks/stage_one.py            # full table
    python benchmarks/stage_one.py --quick    # T = 1000 only
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time


def run_one(system: str, n_times: int) -> dict:
    import numpy as np
    import pysindy as ps
    import torch

    from latentsindy import DynamicSINDy, systems

    torch.set_num_threads(2)
    base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    if system == "oscillator":
        data = systems.harmonic_oscillator(A=systems.Switch(-1.0, -4.0, at=12.5), B=1.0,
                                           t_end=25.0, n_times=n_times, noise=0.01)
        x, names, lib = data.x, ["x", "y"], ps.PolynomialLibrary(degree=2)
        truth = data.parameters["A"]
        pick = ("x", "y")
    else:
        data = systems.lotka_volterra(t_end=20.0 * n_times / 2000, n_times=n_times, noise=0.01)
        x, names = data.x[:, :1], ["x"]
        lib = ps.PolynomialLibrary(degree=3, include_bias=False)
        truth = 1.0 - 0.1 * data.x_clean[:, 1]  # h = alpha - beta * y
        pick = ("x", "x")
    start = time.perf_counter()
    model = DynamicSINDy(lib, verbose=False).fit(x, data.t, feature_names=names)
    coefs = model.coefficients(n_samples=32)
    wall = time.perf_counter() - start
    peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base_rss) / 1024.0
    est = coefs.term(*pick) if pick in coefs.active_terms() else np.zeros_like(truth)
    r2 = 1 - np.sum((est - truth) ** 2) / np.sum((truth - truth.mean()) ** 2)
    return {"system": system, "T": n_times, "wall_s": wall, "peak_mb": peak_mb,
            "params": model.n_parameters_, "r2": float(r2),
            "terms": len(coefs.active_terms())}


def main(lengths=(1000, 2000, 8000)) -> list[dict]:
    rows = []
    for system in ("oscillator", "lotka_volterra"):
        for n in lengths:
            out = subprocess.run([sys.executable, __file__, "--one", system, str(n)],
                                 capture_output=True, text=True, check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print("| system | T | wall time (s) | peak memory (MB) | parameters | R^2 of varying "
          "coefficient | terms |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['system']} | {r['T']} | {r['wall_s']:.1f} | {r['peak_mb']:.0f} | "
              f"{r['params']} | {r['r2']:.4f} | {r['terms']} |")
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--one", nargs=2, metavar=("SYSTEM", "T"))
    args = parser.parse_args()
    from _runner import environment  # noqa: E402

    print(environment(), flush=True)  # what the numbers depend on, first
    if args.one:
        print(json.dumps(run_one(args.one[0], int(args.one[1]))))
    else:
        main((1000,) if args.quick else (1000, 2000, 8000))
