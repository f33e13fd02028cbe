"""Tutorial: find the predator from prey counts alone (Lotka-Volterra).

Only the prey x is observed. Dynamic SINDy writes xdot = x * h(t); the hidden state
h = alpha - beta * y is an affine image of the unmeasured predator y, and pysindy
closes the system: hdot = gamma*alpha - gamma*h - delta*alpha*x + delta*x*h.

Run:  python examples/lotka_volterra.py   (figure in examples/output/)
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pysindy as ps

from latentsindy import discover_hidden, systems

ALPHA, BETA, GAMMA, DELTA = 1.0, 0.1, 1.5, 0.075
# the hidden equation after the change of variables h = alpha - beta * y
TRUE_HIDDEN = {"1": GAMMA * ALPHA, "h": -GAMMA, "x": -DELTA * ALPHA, "h x": DELTA}


def hidden_equation_errors(result) -> tuple[dict, list, list]:
    """Relative error of each true term of dh/dt, plus extra and missing terms."""
    names = result.sindy.get_feature_names()
    row = result.sindy.coefficients()[0]
    found = {n: c for n, c in zip(names, row, strict=True) if c != 0}
    errors = {n: abs(found[n] / v - 1) for n, v in TRUE_HIDDEN.items() if n in found}
    extra = sorted(set(found) - set(TRUE_HIDDEN))
    missing = sorted(set(TRUE_HIDDEN) - set(found))
    return errors, extra, missing


def main(noise_levels=(0.0, 0.01), n_times=2000, training=None, output="examples/output",
         verbose=True, seed=0):
    results = {}
    for noise in noise_levels:
        data = systems.lotka_volterra(ALPHA, BETA, GAMMA, DELTA, n_times=n_times, noise=noise,
                                      seed=seed)
        result = discover_hidden(
            data.x[:, :1], ps.PolynomialLibrary(degree=3, include_bias=False), t=data.t,
            feature_names=["x"], hidden_names=["h"], training=training, verbose=verbose,
            seed=seed)
        r2 = result.compare_hidden(data.x_clean[:, 1]).r2[0]
        errors, extra, missing = hidden_equation_errors(result)
        sim = result.simulate()
        nrmse = (np.sqrt(np.mean((sim.x[:, 0] - data.x_clean[:, 0]) ** 2))
                 / np.std(data.x_clean[:, 0])) if sim.success else np.inf
        results[noise] = {"result": result, "data": data, "r2": r2, "errors": errors,
                          "extra": extra, "missing": missing, "simulation": sim,
                          "nrmse": nrmse}
        print(f"\n=== noise {noise:.0%} of the signal's std, T={n_times} ===")
        print(result.summary())
        print("truth:      dh/dt = " + " + ".join(f"{v:.5g}*{k}" for k, v in
                                                   TRUE_HIDDEN.items()))
        print(f"hidden vs true predator: R^2 = {r2:.5f}")
        print("coefficient errors: " + ", ".join(f"{k}: {v:.2%}" for k, v in errors.items())
              + f"; extra {extra or 'none'}; missing {missing or 'none'}")
        print(f"closed system reproduces x: normalised RMSE {nrmse:.4f} ({sim.status})")
    if output:
        _figure(results, Path(output) / "lotka_volterra.png")
    return results


def _figure(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 2, figsize=(11, 3.2 * len(results)), squeeze=False)
    for row, (noise, r) in zip(axes, results.items(), strict=True):
        res, data = r["result"], r["data"]
        y_from_h = (ALPHA - res.hidden[:, 0]) / BETA
        row[0].plot(data.t, data.x_clean[:, 1], "k", lw=2, label="true predator y")
        row[0].plot(data.t, y_from_h, "C1--", label="inferred (alpha - h) / beta")
        row[0].set_title(f"noise {noise:.0%}: hidden R^2 = {r['r2']:.4f}")
        row[0].legend(loc="upper right")
        row[1].plot(data.t, data.x[:, 0], ".", ms=2, color="0.6", label="observed prey")
        row[1].plot(r["simulation"].t, r["simulation"].x[:, 0], "C0", label="closed system")
        row[1].set_title("simulated closed system vs data")
        row[1].legend(loc="upper right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"\nfigure: {path}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 0.01])
    parser.add_argument("--n-times", type=int, default=2000)
    args = parser.parse_args()
    main(tuple(args.noise), args.n_times)
