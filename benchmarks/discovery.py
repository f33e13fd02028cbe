"""Randomised discovery benchmark: ``discover_hidden`` at default settings on families of
systems with hidden states, next to a ratio baseline and an oracle.

For every family (``_families.py``), draw, and noise level (a fraction of each state's
std): one ``discover_hidden`` call with the family's library and nothing else set; the
result is scored in its own variables against the truth moved into them
(``_scoring.py``): the number of hidden states, extra and missing terms in every
equation, the largest relative error of the hidden equations' coefficients, R^2 of the
true hidden variables from the reported hidden series (best affine map), wall time, and
how often a wrong structure was reported with confidence (``result.confident``: no
equally good alternative and no failed check).

* ratio baseline (prey-only Lotka-Volterra only): h = xdot / x from the same
  differentiator, then the same cross-validated closure with its integral refit.
* oracle: the true hidden variables (as latentsindy should report them) observed with
  the same relative noise, differentiated the same way, the same closure.

Usage::

    python benchmarks/discovery.py                 # full: 10 draws, noise 0/1/5/10%
    python benchmarks/discovery.py --quick         # 3 draws at 1% noise
    python benchmarks/discovery.py --families lotka_volterra --draws 5 --noise 0.01 0.05
    python benchmarks/discovery.py --jobs 14       # 14 processes of one thread each
"""

from __future__ import annotations

import argparse
import sys
import time
import traceback
import warnings
from pathlib import Path

import numpy as np
import pysindy as ps
import sympy as sp

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _families import ALL_FAMILIES, FAMILIES, draw  # noqa: E402
from _runner import run_all  # noqa: E402
from _scoring import (  # noqa: E402
    _natural,
    natural_series,
    score,
    score_hidden_equations,
    truth_in_variables,
)

from latentsindy import discover_hidden  # noqa: E402
from latentsindy._core.derivatives import AdaptiveSavitzkyGolay  # noqa: E402
from latentsindy._stage_two.fit.field import ParametricSystem  # noqa: E402
from latentsindy._stage_two.fit.refine import Problem  # noqa: E402
from latentsindy._stage_two.propose.closure import fit_closure  # noqa: E402

NOISE = (0.0, 0.01, 0.05, 0.1)


def _closure_rhs(closure, hidden_names, observed_names):
    symbols = {n: sp.Symbol(n, real=True) for n in list(hidden_names) + list(observed_names)}
    out = {}
    for k, h in enumerate(hidden_names):
        expr = sp.Integer(0)
        for name, c in zip(closure.feature_names, closure.coef[k], strict=True):
            if c != 0:
                term = sp.Integer(1)
                if name != "1":
                    for part in name.split(" "):
                        base, _, power = part.partition("^")
                        term *= symbols[base] ** int(power or 1)
                expr += float(c) * term
        out[h] = expr
    return out


def _closure_on(series, d, names, noise, seed):
    """The closure fitted on given hidden series (noise added relative to their std)."""
    rng = np.random.default_rng(seed)
    noisy = series + noise * series.std(axis=0) * rng.standard_normal(series.shape)
    diff_h = AdaptiveSavitzkyGolay()
    hdot = diff_h(noisy, d.t)
    diff_x = AdaptiveSavitzkyGolay()
    diff_x(d.observed, d.t)
    span = max(max(diff_h.windows_), max(diff_x.windows_))
    closure = fit_closure([diff_h.smoothed_x_], [hdot], [diff_x.smoothed_x_], [d.t],
                          ps.PolynomialLibrary(degree=2), names, d.observed_names, span=span)
    return _closure_rhs(closure, names, d.observed_names)


def oracle(d, noise, seed):
    """Closure on the noisy true hidden series, then (``refined``) the same refinement
    as latentsindy's with every state observed: the hidden variable measured."""
    series, names = natural_series(d)
    start = time.perf_counter()
    found = _closure_on(series, d, names, noise, seed)
    extra, missing, err = score_hidden_equations(found, d, names)
    out = {"error": err, "exact": extra == 0 and missing == 0}
    try:
        refined = _refined_oracle(d, series, names, found, noise, seed)
        out["refined_error"] = score_hidden_equations(refined, d, names)[2]
    except Exception as exc:  # noqa: BLE001 - reported, not fatal
        out["refined_error"] = np.inf
        out["refined_failed"] = f"{type(exc).__name__}: {exc}"
    out["wall"] = time.perf_counter() - start
    return out


def _refined_oracle(d, series, names, found, noise, seed):
    """Multiple-shooting fit of the true observed structure plus the oracle closure's
    hidden equations, to all states (observed and the noisy hidden series)."""
    rng = np.random.default_rng(seed)
    noisy = series + noise * series.std(axis=0) * rng.standard_normal(series.shape)
    truth = truth_in_variables(d, _natural(d), names)
    state_names = list(d.observed_names) + names
    symbols = [sp.Symbol(n, real=True) for n in state_names]
    values = d.truth["values"]
    rows = {}
    for n in d.observed_names:
        poly = sp.Poly(sp.expand(truth[n]), *symbols)
        rows[n] = {sp.Mul(*[s**e for s, e in zip(symbols, mono, strict=True)]): coef
                   for mono, coef in poly.as_dict().items() if sp.simplify(coef) != 0}
    for h in names:
        poly = sp.Poly(sp.expand(found[h]), *symbols)
        rows[h] = {sp.Mul(*[s**e for s, e in zip(symbols, mono, strict=True)]): coef
                   for mono, coef in poly.as_dict().items()}
    features = sorted({f for r in rows.values() for f in r}, key=sp.default_sort_key)
    coef = np.zeros((len(state_names), len(features)))
    free = np.zeros_like(coef, dtype=bool)
    definitions = _definitions(d, names, symbols)
    for i, n in enumerate(state_names):
        for f, c in rows[n].items():
            j = features.index(f)
            coef[i, j] = float(sp.sympify(c).subs(values))
            free[i, j] = (n, f) not in definitions
    system = ParametricSystem(tuple(state_names), len(state_names), tuple(features), coef, free)
    data = np.hstack([d.observed, noisy])
    smooth = AdaptiveSavitzkyGolay()
    smooth(data, d.t)
    fit = Problem(system, [d.t], [data], [smooth.smoothed_x_]).fit()
    return {h: fit.system.rhs()[h] for h in names}


def _definitions(d, names, symbols):
    """Coefficients fixed by the hidden variables' definitions (the pivot's 1, a rate's
    1) as (state, feature) pairs."""
    fixed = set()
    by_name = dict(zip(list(d.observed_names) + names, symbols, strict=True))
    for k, item in enumerate(d.natural):
        if item == "rate":
            fixed.add((names[k - 1], by_name[names[k]]))
        else:
            state, feature = item
            term = by_name[names[k]]
            if feature != "1":
                for part in feature.split(" "):
                    base, _, power = part.partition("^")
                    term *= by_name[base] ** int(power or 1)
            fixed.add((state, term))
    return fixed


def ratio_baseline(d):
    """h = xdot / x (prey-only Lotka-Volterra), then the same closure."""
    start = time.perf_counter()
    diff = AdaptiveSavitzkyGolay()
    xdot = diff(d.observed, d.t)
    h = xdot / diff.smoothed_x_
    hdot = AdaptiveSavitzkyGolay()(h, d.t)
    closure = fit_closure([h], [hdot], [diff.smoothed_x_], [d.t],
                          ps.PolynomialLibrary(degree=2), ["h0"], d.observed_names,
                          span=max(diff.windows_))
    found = _closure_rhs(closure, ["h0"], d.observed_names)
    extra, missing, err = score_hidden_equations(found, d, ["h0"])
    return {"error": err, "exact": extra == 0 and missing == 0,
            "wall": time.perf_counter() - start}


def run_one(family, index, noise, verbose=False):
    d = draw(family, index, noise)
    row = {"family": family, "draw": index, "noise": noise, "params": d.params}
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = discover_hidden(d.observed, ALL_FAMILIES[family].library(), t=d.t,
                                     feature_names=list(d.observed_names), verbose=verbose)
        row["wall"] = time.perf_counter() - start
        row["timings"] = result.timings
        row.update(score(result, d))
        row["uncertain"] = bool(result.uncertain)
        row["confident"] = result.confident
        row["summary"] = result.summary()
    except Exception as err:  # noqa: BLE001 - a failure is a benchmark outcome
        row.update(wall=time.perf_counter() - start, failed=f"{type(err).__name__}: {err}",
                   exact=False, confident=False, error=np.inf, r2=np.nan, n_hidden=0,
                   n_hidden_true=len(d.truth["hidden"]))
        if verbose:
            traceback.print_exc()
    row["oracle"] = oracle(d, noise, 2000 + index)
    if family == "lotka_volterra":
        row["ratio"] = ratio_baseline(d)
    return row


def _pct(v):
    return "inf" if not np.isfinite(v) else f"{100 * v:.2f}%"


def table(rows):
    lines = ["| family | noise | draws | hidden states right | exact structure | hidden R^2 "
             "median / worst | hidden-eq. error median / worst | wrong yet confident | "
             "ratio baseline median | oracle median: closure / refined | wall median / max (s) |",
             "|---" * 11 + "|"]
    keys = sorted({(r["family"], r["noise"]) for r in rows},
                  key=lambda k: (list(ALL_FAMILIES).index(k[0]), k[1]))
    for fam, noise in keys:
        rs = [r for r in rows if r["family"] == fam and r["noise"] == noise]
        n = len(rs)
        right = sum(r["n_hidden"] == r["n_hidden_true"] for r in rs)
        exact = sum(bool(r["exact"]) for r in rs)
        r2 = np.array([r["r2"] for r in rs], dtype=float)
        err = np.array([r["error"] for r in rs], dtype=float)
        ratio = [r["ratio"]["error"] for r in rs if "ratio" in r]
        orc = [r["oracle"]["error"] for r in rs]
        orc_r = [r["oracle"].get("refined_error", np.inf) for r in rs]
        walls = [r["wall"] for r in rs]
        overconfident = sum(not r["exact"] and r.get("confident", True) for r in rs)
        lines.append(
            f"| {fam} | {noise:.0%} | {n} | {right}/{n} | {exact}/{n} | "
            f"{np.nanmedian(r2):.4f} / {np.nanmin(r2):.4f} | "
            f"{_pct(np.median(err))} / {_pct(np.max(err))} | {overconfident}/{n} | "
            f"{_pct(np.median(ratio)) if ratio else '-'} | {_pct(np.median(orc))} / "
            f"{_pct(np.median(orc_r))} | {np.median(walls):.1f} / {np.max(walls):.1f} |")
    return "\n".join(lines)


# the columns of the time split: stage one (its parts together), then stage two's stages
SPLIT = {"stage one": ("differentiation", "stage one: exact model", "stage one: generator",
                       "stage one: posterior samples"),
         "generator": ("stage one: generator",),
         "proposals and closure": ("smoothing", "proposals", "closure"),
         "refinement": ("refinement",), "term selection": ("term selection",),
         "held-out score": ("held-out score",), "restatements": ("restatements",),
         "checks and other": ("checks and result", "other",
                              "waiting for the second process")}


def time_split(rows):
    """Median wall seconds by stage per family and noise (``result.timings``)."""
    lines = ["| family | noise | wall | " + " | ".join(SPLIT) + " |",
             "|---" * (3 + len(SPLIT)) + "|"]
    keys = sorted({(r["family"], r["noise"]) for r in rows if "timings" in r},
                  key=lambda k: (list(ALL_FAMILIES).index(k[0]), k[1]))
    for fam, noise in keys:
        rs = [r for r in rows if r["family"] == fam and r["noise"] == noise and "timings" in r]
        cells = [np.median([sum(r["timings"].get(s, 0.0) for s in stages) for r in rs])
                 for stages in SPLIT.values()]
        lines.append(f"| {fam} | {noise:.0%} | {np.median([r['wall'] for r in rs]):.1f} | "
                     + " | ".join(f"{c:.1f}" for c in cells) + " |")
    return "\n".join(lines)


def main(families=None, draws=10, noise=NOISE, out=None, verbose=False, jobs=1):
    families = list(families or FAMILIES)
    tasks = [(fam, k, nz, verbose) for fam in families for nz in noise
             for k in range(draws)]

    def report(row):
        print(f"{row['family']:20s} noise {row['noise']:.0%} draw {row['draw']}: hidden "
              f"{row['n_hidden']}/{row['n_hidden_true']} exact {row['exact']} "
              f"confident {row.get('confident')} error "
              f"{_pct(row['error'])} R^2 {row['r2']:.4f} ({row['wall']:.1f} s)"
              + (f" FAILED {row['failed']}" if "failed" in row else ""), flush=True)

    rows = run_all(run_one, tasks, report, jobs, out)
    print()
    print(table(rows))
    print("\nWhere the time goes (median seconds; stage one includes its generator):\n")
    print(time_split(rows))
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 draws at 1%% noise")
    parser.add_argument("--families", nargs="+", choices=list(ALL_FAMILIES),
                        help="default: every family of FAMILIES (the held-out UNSEEN "
                             "ones run by name only)")
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--noise", type=float, nargs="+", default=list(NOISE))
    parser.add_argument("--out", help="write every row as JSON here")
    parser.add_argument("--verbose", action="store_true")
    parser.add_argument("--jobs", type=int, default=1, help="processes (one thread each)")
    args = parser.parse_args()
    from _runner import environment  # noqa: E402

    print(environment(), flush=True)  # what the numbers depend on, first
    if args.quick:
        args.draws, args.noise = 3, [0.01]
    main(args.families, args.draws, tuple(args.noise), args.out, args.verbose, args.jobs)
