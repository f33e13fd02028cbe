"""Tutorial: two hidden variables from one coordinate (Lorenz seen through x alone).
=================================================================================

Only x(t) of the Lorenz system is measured (1% noise); y and z are not. In
``xdot = sigma (y - x)`` the constant's coefficient varies in time: a first hidden
state h0. Its own law needs a second one, the coefficient of x in ``dh0/dt``, which
varies as well: discovery applied again to the augmented system (nested discovery).
The closed system comes back in the variables it was found in; with ``dx/dt = h0``
(h0 = sigma (y - x), h1 = sigma (rho - z - 1)) the truth reads

    dx/dt  = h0
    dh0/dt = -(1 + sigma) h0 + x h1
    dh1/dt = -x h0 - beta h1 - sigma x^2 + beta sigma (rho - 1)

and with ``dx/dt = h0 - sigma x`` (h0 = sigma y, h1 = sigma (rho - z)) it reads
``dh0/dt = -h0 + x h1``, ``dh1/dt = -x h0 - beta h1 + beta sigma rho``: the script
compares the found coefficients with whichever form was found.

Run:  python examples/lorenz_from_x.py   (figure in examples/output/)

.. image:: /figures/lorenz_from_x.png
   :alt: both hidden states against the true y and z
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pysindy as ps
import sympy as sp

from latentsindy import discover_hidden, systems

OUTPUT = Path(__file__).resolve().parent / "output"  # beside this script, from any folder

SIGMA, RHO, BETA = 10.0, 28.0, 8.0 / 3.0
X, H0, H1 = sp.symbols("x h0 h1", real=True)


def truth(absorbed: bool) -> dict:
    """The true closed system in the found variables: ``absorbed`` when the found
    dx/dt has no x term (h0 = sigma (y - x)), else h0 = sigma y."""
    if absorbed:
        return {"x": {H0: 1.0},
                "h0": {H0: -(1 + SIGMA), X * H1: 1.0},
                "h1": {X * H0: -1.0, H1: -BETA, X**2: -SIGMA,
                       sp.Integer(1): BETA * SIGMA * (RHO - 1)}}
    return {"x": {H0: 1.0, X: -SIGMA},
            "h0": {H0: -1.0, X * H1: 1.0},
            "h1": {X * H0: -1.0, H1: -BETA, sp.Integer(1): BETA * SIGMA * RHO}}


def true_hidden(data, absorbed: bool) -> np.ndarray:
    """The true series of h0 and h1 in the found variables."""
    x, y, z = data.x_clean.T
    shift = 1.0 if absorbed else 0.0
    return np.column_stack([SIGMA * (y - shift * x), SIGMA * (RHO - z - shift)])


def simulate_data(noise, seed):
    """Lorenz on its attractor (a burn-in of 10 time units first), 2000 samples over 20."""
    burn = systems.lorenz(SIGMA, RHO, BETA, t_end=10.0, n_times=1001)
    return systems.lorenz(SIGMA, RHO, BETA, t_end=20.0, n_times=2000,
                          x0=burn.x_clean[-1], noise=noise, seed=seed)


def compare(result) -> dict:
    """Per equation of the found system against the truth in its variables: the extra
    and missing terms and the largest relative coefficient error."""
    if len(result.hidden_names) != 2:
        return {"absorbed": None, "errors": {}, "extra": ["not two hidden states"],
                "missing": []}
    names = dict(zip(result.hidden_names, ("h0", "h1"), strict=True))
    rename = {sp.Symbol(n, real=True): sp.Symbol(m, real=True) for n, m in names.items()}
    found = {names.get(s, s): {sp.sympify(f).xreplace(rename): v
                               for f, v in result.equation(s).items()}
             for s in result.state_names}
    absorbed = X not in found["x"]
    true = truth(absorbed)
    errors, extra, missing = {}, [], []
    for state, law in true.items():
        extra += [f"{state}: {f}" for f in set(found[state]) - set(law)]
        missing += [f"{state}: {f}" for f in set(law) - set(found[state])]
        common = [f for f in law if f in found[state]]
        errors[state] = max((abs(found[state][f] / law[f] - 1) for f in common), default=0.0)
    return {"absorbed": absorbed, "errors": errors, "extra": sorted(extra),
            "missing": sorted(missing)}


def main(noise=0.01, output=OUTPUT, verbose=True, seed=0):
    data = simulate_data(noise, seed)
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=2), t=data.t,
                             feature_names=["x"], verbose=verbose, seed=seed)
    report = compare(result)
    r2 = result.compare_hidden(data.x_clean[:, 1:], with_observed=True).r2
    print(result.summary())
    print(f"\ntruth (sigma={SIGMA}, rho={RHO}, beta={BETA:.4f}), in the found variables:")
    if report["absorbed"] is not None:
        for state, law in truth(report["absorbed"]).items():
            terms = " + ".join(f"{v:.4g}*{f}" for f, v in law.items())
            print(f"  d{state}/dt = " + terms.replace("+ -", "- "))
    print(f"R^2 of y and z from the hidden and observed states: {np.round(r2, 5)}")
    print("largest coefficient error per equation: "
          + ", ".join(f"{k}: {v:.2%}" for k, v in report["errors"].items())
          + f"; extra {report['extra'] or 'none'}; missing {report['missing'] or 'none'}")
    if output and report["absorbed"] is not None:
        _figure(result, data, report["absorbed"], Path(output) / "lorenz_from_x.png")
    return {"result": result, "data": data, "r2": r2, **report}


def _figure(result, data, absorbed, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hidden = true_hidden(data, absorbed)
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    axes[0].plot(data.t, data.x[:, 0], ".", color="0.5", ms=2, label="measured x (all there is)")
    for ax, k, name in ((axes[1], 0, "h0"), (axes[2], 1, "h1")):
        ax.plot(data.t, hidden[:, k], "k", lw=2, label=f"true {name}")
        ax.plot(result.times, result.hidden[:, k], "C1--", lw=1,
                label=f"found {name} (closed system's trajectory)")
    for ax in axes:
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("t")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"\nfigure: {path}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    main(args.noise, seed=args.seed)
