"""Stage one and discovery on the CPU and on a CUDA device, side by side.

Cases (default settings, 1% noise, each in a fresh process, timing covers the call):

* ``timevae``: ``DynamicSINDy`` (timeVAE) on the oscillator with a switching A(t),
  T = 10^4 samples (dt = 0.025, switch mid-series); fit plus 32 posterior samples;
  R^2 of A(t).
* ``hypersindy``: ``DynamicSINDy(generator="hypersindy")`` on Lorenz with a sigmoid
  sigma(t) (``benchmarks/hypersindy.py``'s series), T = 10^6 by default; fit only;
  seconds per 10k samples processed and the terms kept (Lorenz has 7).
* ``discover``: ``discover_hidden`` on prey-only Lotka-Volterra, T = 2000; the
  closed law's structure is compared with the truth.

Memory is the peak of the device's allocator on CUDA and the resident-set growth on the
CPU. Usage::

    python benchmarks/devices.py --devices cpu cuda
    python benchmarks/devices.py --devices cuda --cases hypersindy --samples 100000
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def _memory(device, base_rss):
    import torch

    if device.startswith("cuda"):
        return torch.cuda.max_memory_allocated() / 2**20
    return (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base_rss) / 1024.0


def _sync(device):
    import torch

    if device.startswith("cuda"):
        torch.cuda.synchronize()


def run_timevae(device, n_times):
    import pysindy as ps

    from latentsindy import DynamicSINDy, systems

    t_end = 0.025 * n_times
    data = systems.harmonic_oscillator(A=systems.Switch(-1.0, -4.0, at=t_end / 2), B=1.0,
                                       t_end=t_end, n_times=n_times, noise=0.01, seed=1)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), device=device, verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(n_samples=32)
    _sync(device)
    wall = time.perf_counter() - start
    truth = data.parameters["A"]
    est = coefs.term("x", "y") if ("x", "y") in coefs.active_terms() else 0.0 * truth
    r2 = 1 - np.sum((est - truth) ** 2) / np.sum((truth - truth.mean()) ** 2)
    return {"wall_s": wall, "memory_mb": _memory(device, base),
            "result": f"R^2 of A(t) {r2:.4f}, {len(coefs.active_terms())} terms"}


def run_hypersindy(device, n_times):
    sys.path.insert(0, HERE)
    from hypersindy import DT, lorenz_series

    from latentsindy import DynamicSINDy

    x = lorenz_series(n_times)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    model = DynamicSINDy(generator="hypersindy", device=device, verbose=False).fit(
        x, DT, feature_names=["x", "y", "z"])
    _sync(device)
    wall = time.perf_counter() - start
    epochs = len({(h["phase"], h.get("epoch")) for h in model.history_ if "epoch" in h})
    terms = ", ".join(f"{model.feature_names_[j]} in d{model.state_names_[i]}"
                      for i, j in zip(*np.nonzero(model.support_), strict=True))
    return {"wall_s": wall, "memory_mb": _memory(device, base),
            "result": f"{epochs} epochs, {wall / (epochs * n_times / 1e4):.2f} s per 10k "
                      f"samples, {int(model.support_.sum())} terms ({terms})"}


def run_discover(device, n_times):
    import pysindy as ps
    import sympy as sp

    from latentsindy import discover_hidden, systems

    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=n_times,
                                  t_end=20.0 * n_times / 2000, noise=0.01, seed=1)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    start = time.perf_counter()
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3, include_bias=False),
                             t=data.t, feature_names=["x"], device=device, verbose=False)
    _sync(device)
    wall = time.perf_counter() - start
    law = "; ".join(f"d{n}/dt = {sp.sympify(e).evalf(4)}" for n, e in result.rhs.items())
    return {"wall_s": wall, "memory_mb": _memory(device, base),
            "result": f"confident {result.confident}: {law}"}


CASES = {"timevae": (run_timevae, 10_000), "hypersindy": (run_hypersindy, 1_000_000),
         "discover": (run_discover, 2000)}


def main(devices=("cpu", "cuda"), cases=tuple(CASES), samples=None) -> list[dict]:
    rows = []
    for case in cases:
        n = samples or CASES[case][1]
        for device in devices:
            out = subprocess.run([sys.executable, __file__, "--one", case, device, str(n)],
                                 capture_output=True, text=True)
            if out.returncode != 0:
                row = {"case": case, "device": device, "T": n, "error": out.stderr[-2000:]}
            else:
                row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(json.dumps(row), flush=True)
    print("\n| case | T | device | threads | wall time | peak memory | result |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            print(f"| {r['case']} | {r['T']:,} | {r['device']} | | failed | | "
                  f"{r['error'].splitlines()[-1] if r['error'] else ''} |")
            continue
        print(f"| {r['case']} | {r['T']:,} | {r['device_name']} | {r['threads']} | "
              f"{r['wall_s']:.1f} s | {r['memory_mb']:.0f} MB | {r['result']} |")
    return rows


def run_one(case, device, n_times):
    import torch

    run, _ = CASES[case]
    name = (torch.cuda.get_device_name(torch.device(device)) if device.startswith("cuda")
            else "cpu")
    return {"case": case, "device": device, "device_name": name, "T": n_times,
            "threads": torch.get_num_threads()} | run(device, n_times)


if __name__ == "__main__":
    if len(sys.argv) == 5 and sys.argv[1] == "--one":
        print(json.dumps(run_one(sys.argv[2], sys.argv[3], int(sys.argv[4]))))
    else:
        parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
        parser.add_argument("--devices", nargs="+", default=["cpu", "cuda"])
        parser.add_argument("--cases", nargs="+", choices=list(CASES), default=list(CASES))
        parser.add_argument("--samples", type=int, help="one length for every case")
        args = parser.parse_args()
        from _runner import environment  # noqa: E402

        print(environment(), flush=True)  # what the numbers depend on, first
        main(args.devices, args.cases, args.samples)
