"""Dynamic HyperSINDy on long series: wall time per 10k samples and peak memory.

Fits ``DynamicSINDy(generator="hypersindy")`` at default settings on Lorenz with a
sigmoid sigma(t) (1% noise, dt = 0.01) of 10k, 100k and 1M samples, each in a fresh
process, and prints a Markdown table:

* fit time, and passes over the series (epochs) it made;
* wall time per 10k samples processed (fit time / (epochs x T / 10k));
* peak resident memory of the process (``ru_maxrss``, what the user's machine must
  hold, imports included) and its growth over the process after imports.

The data are integrated once (LSODA) and shared with the runs through a ``.npy``
file, so the timing covers only ``fit``.

Usage::

    python benchmarks/hypersindy.py            # 10k, 100k, 1M
    python benchmarks/hypersindy.py --quick    # 10k only
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

DT = 0.01


def lorenz_series(n_times: int, seed: int = 0) -> np.ndarray:
    """Lorenz with sigma rising 8 -> 14 mid-series (LSODA, rtol 1e-8), 1% noise."""
    from scipy.integrate import odeint

    t_mid = n_times * DT / 2

    def rhs(s, t):
        sigma = 8.0 + 6.0 / (1.0 + np.exp(np.clip(-0.5 * (t - t_mid), -700.0, 700.0)))
        x, y, z = s
        return [sigma * (y - x), x * (28.0 - z) - y, x * y - 8.0 / 3.0 * z]

    t = np.arange(n_times) * DT
    out = odeint(rhs, [-8.0, 7.0, 27.0], t, rtol=1e-8, atol=1e-8, mxstep=100_000)
    rng = np.random.default_rng(seed)
    return out + 0.01 * out.std(axis=0) * rng.standard_normal(out.shape)


def run_one(path: str, n_times: int) -> dict:
    import torch

    from latentsindy import DynamicSINDy

    torch.set_num_threads(2)
    x = np.load(path, mmap_mode="r")[:n_times]
    x = np.array(x)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    model = DynamicSINDy(generator="hypersindy", verbose=False).fit(
        x, DT, feature_names=["x", "y", "z"])
    wall = time.perf_counter() - start
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    epochs = len({(h["phase"], h.get("epoch")) for h in model.history_ if "epoch" in h})
    return {"n_times": n_times, "fit_s": wall, "epochs": epochs,
            "s_per_10k": wall / (epochs * n_times / 10_000),
            "peak_mb": peak / 1024.0, "growth_mb": (peak - base) / 1024.0,
            "terms": int(model.support_.sum())}


def main(sizes=(10_000, 100_000, 1_000_000)) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "lorenz.npy")
        np.save(path, lorenz_series(max(sizes)))
        for n in sizes:
            out = subprocess.run([sys.executable, __file__, "--one", path, str(n)],
                                 capture_output=True, text=True, check=True)
            rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
            print(rows[-1], flush=True)
    print("\n| samples | fit time | epochs | s per 10k samples | peak RSS | growth after "
          "imports | terms |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['n_times']:,} | {r['fit_s']:.1f} s | {r['epochs']} | {r['s_per_10k']:.2f} | "
              f"{r['peak_mb']:.0f} MB | {r['growth_mb']:.0f} MB | {r['terms']} |")
    return rows


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--one":
        print(json.dumps(run_one(sys.argv[2], int(sys.argv[3]))))
    else:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
        parser.add_argument("--quick", action="store_true", help="10k samples only")
        args = parser.parse_args()
        from _runner import environment  # noqa: E402

        print(environment(), flush=True)  # what the numbers depend on, first
        main((10_000,) if args.quick else (10_000, 100_000, 1_000_000))
