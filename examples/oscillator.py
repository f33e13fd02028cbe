"""Tutorial: a coefficient that drifts becomes a state with its own law (oscillator).
==================================================================================

xdot = A y, ydot = B(t) x with A = -4 and B(t) a logistic sigmoid from 2 to 3. Both x
and y are observed; B(t) is not. Dynamic SINDy finds that only B varies, turns it into
a hidden state, and stage two recovers its law: Bdot = -6 + 5B - B^2 (the paper reports
-5.875 + 4.903B - 0.981B^2).

Run:  python examples/oscillator.py   (figure in examples/output/)

.. image:: /figures/oscillator.png
   :alt: the hidden coefficient B(t) and its law
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pysindy as ps
import sympy as sp

from latentsindy import discover_hidden, systems

OUTPUT = Path(__file__).resolve().parent / "output"  # beside this script, from any folder

B = sp.Symbol("B", real=True)
TRUE_HIDDEN = {sp.Integer(1): -6.0, B: 5.0, B**2: -1.0}


def simulate_data(n_times, noise, seed):
    # B = 2 + s with s logistic: Bdot = s (1 - s) = -(B - 2)(B - 3) = -6 + 5B - B^2
    return systems.harmonic_oscillator(A=-4.0, B=systems.Sigmoid(2.0, 3.0, at=5.0),
                                       t_end=10.0, n_times=n_times, x0=(1.0, 0.0),
                                       noise=noise, seed=seed)


def main(noise_levels=(0.0, 0.01), n_times=2000, training=None, output=OUTPUT,
         verbose=True, seed=0):
    results = {}
    for noise in noise_levels:
        data = simulate_data(n_times, noise, seed)
        result = discover_hidden(data.x, ps.PolynomialLibrary(degree=2), t=data.t,
                                 feature_names=["x", "y"], hidden_names=["B"],
                                 training=training, verbose=verbose, seed=seed)
        found = result.equation("B") if "B" in result.state_names else {}
        errors = {str(k): abs(found[k] / v - 1) for k, v in TRUE_HIDDEN.items() if k in found}
        extra = sorted(str(k) for k in set(found) - set(TRUE_HIDDEN))
        missing = sorted(str(k) for k in set(TRUE_HIDDEN) - set(found))
        r2 = result.compare_hidden(data.parameters["B"]).r2[0]
        results[noise] = {"result": result, "data": data, "errors": errors, "extra": extra,
                          "missing": missing, "r2": r2}
        print(f"\n=== noise {noise:.0%}, T={n_times} ===")
        print(result.summary())
        print("truth:  dB/dt = -6 + 5*B - B^2   (paper: -5.875 + 4.903*B - 0.981*B^2)")
        print(f"hidden states: {len(result.hidden_names)}; B(t) R^2 = {r2:.5f}")
        print("coefficient errors: " + ", ".join(f"{k}: {v:.2%}" for k, v in errors.items())
              + f"; extra {extra or 'none'}; missing {missing or 'none'}")
    if output:
        _figure(results, Path(output) / "oscillator.png")
        for noise, r in results.items():  # the library's own figures, one per noise level
            tag = f"{round(100 * noise)}pct"
            r["result"].plot(truth=r["data"].parameters["B"],
                             path=Path(output) / f"oscillator_{tag}_result.png")
            r["result"].coefficients.plot(truth={("y", "x"): r["data"].parameters["B"]},
                                          path=Path(output) / f"oscillator_{tag}_stage_one.png")
    return results


def _figure(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(5.5 * len(results), 3.5), squeeze=False)
    for ax, (noise, r) in zip(axes[0], results.items(), strict=True):
        res, data = r["result"], r["data"]
        ax.plot(data.t, data.parameters["B"], "k", lw=2, label="true B(t)")
        ax.plot(res.times, res.hidden[:, 0], "C1--", label="closed system's B")
        band = 2 * res.hidden_std[:, 0]
        ax.fill_between(res.times, res.hidden[:, 0] - band, res.hidden[:, 0] + band,
                        color="C1", alpha=0.3, label="+-2 std")
        ax.set_title(f"noise {noise:.0%}")
        ax.legend(loc="lower right")
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
