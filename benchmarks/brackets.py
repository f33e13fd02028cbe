"""Brackets for stage two on prey-only Lotka-Volterra (T=2000): latentsindy between a
simple baseline and an oracle.

* latentsindy: ``discover_hidden`` at default settings.
* ratio baseline: smooth and differentiate x (the same noise-adaptive differentiator),
  h = xdot / x, then the same cross-validated SINDy on [x, h].
* oracle: the true predator y observed with the same relative noise, differentiated the
  same way, and the same SINDy for y's equation (truth: -gamma y + delta x y).

Columns: R^2 of the hidden state against the true predator after the best affine map,
the largest relative error of the hidden equation's coefficients, extra/missing terms,
wall time. Usage: ``python benchmarks/brackets.py``.
"""

from __future__ import annotations

import time

import numpy as np
import pysindy as ps

from latentsindy import discover_hidden, systems
from latentsindy._closure import fit_closure
from latentsindy._derivatives import AdaptiveSavitzkyGolay

A, B, G, D = 1.0, 0.1, 1.5, 0.075
TRUE_H = {"1": G * A, "h": -G, "x": -D * A, "h x": D}
TRUE_Y = {"y": -G, "y x": D}


def _score(model, truth):
    names = model.get_feature_names()
    found = {n: c for n, c in zip(names, model.coefficients()[0], strict=True) if c != 0}
    errs = [abs(found[n] / v - 1) for n, v in truth.items() if n in found]
    extra = len(set(found) - set(truth))
    missing = len(set(truth) - set(found))
    return (max(errs) if errs else np.inf), extra, missing


def _r2(hidden, truth):
    design = np.column_stack([hidden, np.ones_like(hidden)])
    coef, *_ = np.linalg.lstsq(design, truth, rcond=None)
    return 1 - np.sum((truth - design @ coef) ** 2) / np.sum((truth - truth.mean()) ** 2)


def run(noise, n_times=2000, seed=0):
    data = systems.lotka_volterra(A, B, G, D, n_times=n_times, noise=noise, seed=seed)
    rows = []

    start = time.perf_counter()
    res = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3, include_bias=False),
                          t=data.t, feature_names=["x"], hidden_names=["h"], verbose=False,
                          seed=seed)
    wall = time.perf_counter() - start
    rows.append(("latentsindy", _r2(res.hidden[:, 0], data.x_clean[:, 1]),
                 *_score(res.sindy, TRUE_H), wall))

    start = time.perf_counter()
    diff = AdaptiveSavitzkyGolay()
    xdot = diff(data.x[:, :1], data.t)
    xs = diff.smoothed_x_
    h = xdot / xs
    hdot = AdaptiveSavitzkyGolay()(h, data.t)
    # the same closure as latentsindy's (integral refit over the smoothing window)
    model, _ = fit_closure([h], [hdot], [xs], [data.t], ps.PolynomialLibrary(degree=2),
                           ["h"], ["x"], span=max(diff.windows_))
    wall = time.perf_counter() - start
    rows.append(("ratio baseline", _r2(h[:, 0], data.x_clean[:, 1]), *_score(model, TRUE_H),
                 wall))

    start = time.perf_counter()
    y = data.x[:, 1:2]
    dy = AdaptiveSavitzkyGolay()
    ydot = dy(y, data.t)
    model, _ = fit_closure([dy.smoothed_x_], [ydot], [xs], [data.t],
                           ps.PolynomialLibrary(degree=2), ["y"], ["x"],
                           span=max(dy.windows_))
    wall = time.perf_counter() - start
    rows.append(("oracle (true y, same noise)", _r2(y[:, 0], data.x_clean[:, 1]),
                 *_score(model, TRUE_Y), wall))
    return rows


def main(noise_levels=(0.0, 0.01, 0.05), n_times=2000):
    print("| noise | method | hidden R^2 | max coef. error | extra / missing | wall time (s) |")
    print("|---|---|---|---|---|---|")
    out = {}
    for noise in noise_levels:
        out[noise] = run(noise, n_times)
        for name, r2, err, extra, missing, wall in out[noise]:
            print(f"| {noise:.0%} | {name} | {r2:.5f} | {err:.2%} | {extra} / {missing} | "
                  f"{wall:.1f} |")
    return out


if __name__ == "__main__":
    main()
