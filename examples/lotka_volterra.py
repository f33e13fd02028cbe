"""Tutorial: find the predator from prey counts alone (Lotka-Volterra).
====================================================================

Only the prey x is observed. Dynamic SINDy writes xdot = x * h(t); the hidden state
h = alpha - beta * y is an affine image of the unmeasured predator y. Stage two closes
the system (hdot = gamma*alpha - gamma*h - delta*alpha*x + delta*x*h), refines it by
integrating it against the prey counts, and checks the alternatives it considered.

Run:  python examples/lotka_volterra.py   (figure in examples/output/)

.. image:: /figures/lotka_volterra.png
   :alt: the inferred predator against the truth, and the closed system against the prey
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pysindy as ps
import sympy as sp

from latentsindy import discover_hidden, systems

OUTPUT = Path(__file__).resolve().parent / "output"  # beside this script, from any folder

ALPHA, BETA, GAMMA, DELTA = 1.0, 0.1, 1.5, 0.075
X, H = sp.symbols("x h", real=True)
# the hidden equation after the change of variables h = alpha - beta * y
TRUE_HIDDEN = {sp.Integer(1): GAMMA * ALPHA, H: -GAMMA, X: -DELTA * ALPHA, H * X: DELTA}


def equation_errors(found: dict, truth: dict) -> tuple[dict, list, list]:
    """Relative error of each true term, and the extra and missing terms."""
    errors = {str(k): abs(found[k] / v - 1) for k, v in truth.items() if k in found}
    extra = sorted(str(k) for k in set(found) - set(truth))
    missing = sorted(str(k) for k in set(truth) - set(found))
    return errors, extra, missing


def main(noise_levels=(0.0, 0.01), n_times=2000, training=None, output=OUTPUT,
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
        found = result.equation("h") if "h" in result.state_names else {}
        errors, extra, missing = equation_errors(found, TRUE_HIDDEN)
        sim = result.simulate()
        nrmse = (np.sqrt(np.mean((sim.x[:, 0] - data.x[:, 0]) ** 2))
                 / np.std(data.x[:, 0])) if sim.success else np.inf
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
        print(f"closed system reproduces the prey: normalised RMSE {nrmse:.4f} ({sim.status})")
    if output:
        _figure(results, Path(output) / "lotka_volterra.png")
        for noise, r in results.items():  # the library's own figure, one per noise level
            r["result"].plot(truth=r["data"].x_clean[:, 1], simulation=r["simulation"],
                             path=Path(output) / f"lotka_volterra_{round(100 * noise)}pct"
                                                 "_result.png")
    return results


def _figure(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(results), 2, figsize=(11, 3.2 * len(results)), squeeze=False)
    for row, (noise, r) in zip(axes, results.items(), strict=True):
        res, data = r["result"], r["data"]
        cmp = res.compare_hidden(data.x_clean[:, 1])  # y = (alpha - h) / beta, fitted map
        y_from_h = res.hidden @ cmp.scale[:, 0] + cmp.offset[0]
        band = 2 * np.abs(cmp.scale[0, 0]) * res.hidden_std[:, 0]
        row[0].plot(data.t, data.x_clean[:, 1], "k", lw=2, label="true predator y")
        row[0].plot(data.t, y_from_h, "C1--", label="inferred (affine map of h)")
        row[0].fill_between(data.t, y_from_h - band, y_from_h + band, color="C1", alpha=0.3)
        row[0].set_title(f"noise {noise:.0%}: hidden R^2 = {r['r2']:.4f}")
        row[0].legend(loc="upper right")
        row[1].plot(data.t, data.x[:, 0], ".", ms=2, color="0.6", label="observed prey")
        row[1].plot(r["simulation"].t, r["simulation"].x[:, 0], "C0", label="closed system")
        row[1].set_title(f"closed system vs data: normalised RMSE {r['nrmse']:.3f}")
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
