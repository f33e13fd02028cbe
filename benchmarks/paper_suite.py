"""The seed paper's synthetic experiments, side by side with its baselines.

For every case of ``_paper_cases`` (oscillator with A(t)/B(t) as a switch, four
switches, a sigmoid, two sinusoids, a 7-frequency Fourier series; Lorenz with sigma,
rho or beta as a sigmoid, switch, sinusoid or Fourier series; 1% noise) and every
method at default settings:

* dynamic SINDy (timeVAE at T=2000; dynamic HyperSINDy at T=10,000 for Lorenz);
* group-sparse windowed SINDy, both published variants (``WindowedSINDy``);
* SLDS, rSLDS and SLDS with time as an input (``switching_lds``), where the truth switches;

it reports the R^2 of every varying coefficient (the worst one in the table), the
worst relative error of the constant coefficients, whether the support is exact, the
switch-time error (worst over true switches of the distance to the nearest switch
found, as a share of the series) with the number of switches found (for a sigmoid: where
the estimate crosses halfway between its early and late levels), for the segmentations
the share of samples labelled right, and the wall time; for coefficient series the
band's coverage of the truth (share of samples inside ``lower``..``upper``, worst
varying coefficient), its mean half-width over the actual RMS error and the number of
doubts. Then the uncertainty experiment
(main text 4.2): A and B carry white noise of known standard deviation, and the paper's
two spread estimates and ``DynamicSINDy.coefficient_noise`` are compared with it.

Usage::

    python benchmarks/paper_suite.py            # everything (about 25 minutes, 2 cores)
    python benchmarks/paper_suite.py --quick    # a few cases (about 3 minutes)

Tables go to stdout (Markdown), raw numbers to benchmarks/output/paper_suite.json and
figures (the varying coefficient against the truth, case by case and method by method,
as the paper's figures 2, 4 and 7 show them) to docs/figures/, which the README shows
(``--quick`` puts its figures in benchmarks/output/).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pysindy as ps
import torch
from _paper_cases import (
    constant_terms,
    lorenz_cases,
    make_data,
    oscillator_cases,
    true_labels,
    true_switch_times,
    varying_terms,
)

from latentsindy import DynamicSINDy, systems
from latentsindy.baselines import WindowedSINDy, switch_time_errors, switching_lds

OUT = Path(__file__).parent / "output"
FIGURES = Path(__file__).parent.parent / "docs" / "figures"  # shown in the README
UNCERTAINTY_STDS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.5)


def r2(estimate, truth):
    return float(1.0 - np.sum((estimate - truth) ** 2) / np.sum((truth - truth.mean()) ** 2))


def names(case):
    return ["x", "y"] if case.system == "oscillator" else ["x", "y", "z"]


def score(coefs, case, data, t_end):
    """Metrics of a CoefficientSeries against the case's truth."""
    varying = varying_terms(case, data)
    r2s = {f"{s}:{f}": r2(coefs.term(s, f), v) for (s, f), v in varying.items()}
    consts = constant_terms(data)
    const_err = max((abs(float(np.mean(coefs.term(s, f))) / v - 1)
                     for (s, f), v in consts.items()), default=float("nan"))
    truth_support = sorted(k for k, v in data.terms.items() if np.any(v != 0))
    row = {"r2": r2s, "worst_r2": min(r2s.values()), "const_err": const_err,
           "exact_support": sorted(coefs.active_terms()) == truth_support}
    sw = true_switch_times(case, t_end)
    if sw is not None:
        found = (coefs.switch_times(terms=list(varying)) if case.shape != "sigmoid"
                 else midpoint_crossings(coefs, varying))
        row["switch_err"] = float(switch_time_errors(found, sw).max() / t_end)
        row["switches_found"] = int(found.size)
    if np.any(coefs.upper > coefs.lower):
        inside, ratio = [], []
        for (s, f), v in varying.items():
            lo, hi = coefs.term_band(s, f)
            inside.append(np.mean((lo - 1e-12 <= v) & (v <= hi + 1e-12)))
            error = np.sqrt(np.mean((coefs.term(s, f) - v) ** 2))
            ratio.append(float(np.mean(0.5 * (hi - lo))) / max(error, 1e-300))
        row["coverage"] = float(np.min(inside))  # the worst varying coefficient
        row["width_ratio"] = float(np.max(ratio))
    row["doubts"] = list(coefs.doubts)
    return row


def midpoint_crossings(coefs, varying):
    """Where a sigmoid's estimate crosses halfway between its early and late levels (the
    first 10% and last 10% of the series); a smooth transition has no jump for
    ``switch_times`` to find."""
    (state, feature), _ = next(iter(varying.items()))
    est = coefs.term(state, feature)
    k = max(1, est.size // 10)
    mid = 0.5 * (np.median(est[:k]) + np.median(est[-k:]))
    above = est > mid
    i = np.flatnonzero(np.diff(above.astype(int)))
    return 0.5 * (coefs.times[i] + coefs.times[i + 1])


def run_case(case, seed=0, slds=True):
    data, t_end = make_data(case, seed)
    feature_names = names(case)
    library = ps.PolynomialLibrary(degree=2)
    rows, series = {}, {}
    start = time.perf_counter()
    model = DynamicSINDy(library, generator=case.generator, verbose=False, seed=seed)
    coefs = model.fit(data.x, data.t, feature_names=feature_names).coefficients(n_samples=16)
    label = "dynamic SINDy" + (" (HyperSINDy)" if case.generator == "hypersindy" else "")
    rows[label] = score(coefs, case, data, t_end) | {"time": time.perf_counter() - start}
    series[label] = coefs
    for method in ("stlsq", "group"):
        start = time.perf_counter()
        win = WindowedSINDy(library, method=method).fit(data.x, data.t,
                                                        feature_names=feature_names)
        coefs = win.coefficients()
        label = f"windowed {method}"
        rows[label] = score(coefs, case, data, t_end) | {"time": time.perf_counter() - start,
                                                         "windows": win.n_windows_}
        series[label] = coefs
    labels = true_labels(case, data.t)
    if slds and labels is not None:
        for label, kw in (("SLDS", {"method": "slds"}), ("rSLDS", {"method": "rslds"}),
                          ("SLDS + time", {"method": "slds", "time_input": True})):
            start = time.perf_counter()
            seg = switching_lds(data.x, data.t, seed=seed, **kw)
            found = seg.switch_times
            rows[label] = {
                "switch_err": float(switch_time_errors(found, true_switch_times(
                    case, t_end)).max() / t_end),
                "switches_found": int(found.size), "accuracy": seg.accuracy(labels),
                "time": time.perf_counter() - start}
    return rows, series, data


def uncertainty(stds, seed=0):
    """The paper's two spread estimates against the true coefficient noise."""
    out = []
    for std in stds:
        data = systems.harmonic_oscillator(A=-2.0, B=1.0, t_end=25.0, n_times=2000,
                                           coefficient_noise=std, seed=seed)
        model = DynamicSINDy(ps.PolynomialLibrary(degree=1, include_bias=False),
                             verbose=False, seed=seed)
        # the exact derivative carries the coefficient noise; differentiating x would
        # average it away
        coefs = model.fit(data.x, data.t, x_dot=data.x_dot,
                          feature_names=["x", "y"]).coefficients(n_samples=64)
        i, j = coefs.state_names.index("x"), coefs.feature_names.index("y")
        out.append({"true_std": std,
                    "from_residuals": float(model.coefficient_noise(coefs)[i, j]),
                    "across_samples": float(coefs.noise_across_samples[i, j]),
                    "around_smooth_mean": float(coefs.noise_around_smooth_mean[i, j]),
                    "residual_std": float(np.std(coefs.term("x", "y") - data.parameters["A"]))})
    return out


def table(results):
    lines = ["| case | method | worst R^2 varying | constants max err | exact support | "
             "switch err (share) / found | band coverage | band / error | doubts | "
             "time (s) |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for case, rows in results.items():
        for method, r in rows.items():
            sw = (f"{r['switch_err']:.1%} / {r['switches_found']}" if "switch_err" in r
                  else "")
            if "accuracy" in r:
                sw += f" (acc {r['accuracy']:.2f})"
            support = ("yes" if r.get("exact_support") else
                       "no" if "exact_support" in r else "")
            coverage = f"{r['coverage']:.2f}" if "coverage" in r else ""
            ratio = f"{r['width_ratio']:.2f}" if "width_ratio" in r else ""
            doubts = str(len(r["doubts"])) if r.get("doubts") else ""
            lines.append(f"| {case} | {method} | {r.get('worst_r2', float('nan')):.3f} | "
                         f"{r.get('const_err', float('nan')):.1%} | {support} | {sw} | "
                         f"{coverage} | {ratio} | {doubts} | {r['time']:.1f} |")
    return "\n".join(line.replace("| nan |", "| |").replace("| nan% |", "| |")
                     for line in lines)


def summary(results):
    """The bars of issue 19 over dynamic SINDy's rows."""
    ours = {c: next(r for m, r in rows.items() if m.startswith("dynamic SINDy"))
            for c, rows in results.items()}
    best_baseline = {c: max(r["worst_r2"] for m, r in rows.items() if m.startswith("windowed"))
                     for c, rows in results.items()}
    good = [c for c, r in ours.items() if r["worst_r2"] > 0.9 and r["exact_support"]]
    behind = [c for c, r in ours.items() if r["worst_r2"] < best_baseline[c] - 0.05]
    fitted = [r for c, r in ours.items() if c in good and "coverage" in r]
    cover = np.array([r["coverage"] for r in fitted])
    ratio = np.array([r["width_ratio"] for r in fitted])
    failed = [c for c in ours if c not in good]
    flagged = [c for c in failed if ours[c]["doubts"]]
    false = [c for c in good if ours[c]["doubts"]]
    return "\n".join([
        f"R^2 > 0.9 and exact support: {len(good)} of {len(ours)}; failures {failed}, "
        f"{len(flagged)} of them flagged by a doubt",
        f"more than 0.05 below the better windowed baseline: {behind}",
        f"band coverage over the {len(fitted)} successes: median {np.median(cover):.3f}, "
        f"worst {cover.min():.3f}; half-width / RMS error: median {np.median(ratio):.2f}, "
        f"worst {ratio.max():.2f}",
        f"successes with a doubt: {false}"])


def figure(name, cases, all_series, all_data, folder=FIGURES):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = list(next(iter(all_series.values())))
    fig, axes = plt.subplots(len(cases), len(methods), figsize=(3.2 * len(methods),
                                                                1.7 * len(cases)),
                             squeeze=False, sharex="row")
    for r, (row, case) in enumerate(zip(axes, cases, strict=True)):
        data = all_data[case.name]
        (state, feature), truth = next(iter(varying_terms(case, data).items()))
        for ax, method in zip(row, methods, strict=True):
            coefs = all_series[case.name][method]
            est = coefs.term(state, feature)
            lo, hi = coefs.term_band(state, feature)
            ax.plot(data.t, truth, "k", lw=1.5)
            ax.plot(data.t, est, "C1", lw=1)
            if np.any(hi > lo):
                ax.fill_between(data.t, lo, hi, color="C1", alpha=0.3)
            lo, hi = truth.min(), truth.max()
            ax.set_ylim(lo - 0.6 * (hi - lo), hi + 0.6 * (hi - lo))
            ax.tick_params(labelsize=6)
            if r == 0:
                ax.set_title(method, fontsize=8)
            if method == methods[0]:
                ax.set_ylabel(f"{case.shape}\n{state}:{feature}", fontsize=7)
    fig.tight_layout()
    folder.mkdir(parents=True, exist_ok=True)
    fig.savefig(folder / f"paper_{name}.png", dpi=70)
    plt.close(fig)


GROUPS = ("oscillator", "lorenz", "lorenz_10k")


def main(quick=False, seed=0, only=GROUPS):
    torch.set_num_threads(2)
    groups = {"oscillator": oscillator_cases(), "lorenz": lorenz_cases("timevae"),
              "lorenz_10k": lorenz_cases("hypersindy")}
    groups = {k: v for k, v in groups.items() if k in only}
    if quick and set(only) == set(GROUPS):
        groups = {"oscillator": [c for c in groups["oscillator"]
                                 if c.shape in ("switch", "sinusoids")],
                  "lorenz": [groups["lorenz"][0]], "lorenz_10k": []}
    quick = quick or set(only) != set(GROUPS)  # a part must not overwrite the figures
    results, total = {}, time.perf_counter()
    for group, cases in groups.items():
        all_series, all_data = {}, {}
        for case in cases:
            rows, series, data = run_case(case, seed, slds=group != "lorenz_10k")
            results[case.name] = rows
            all_series[case.name], all_data[case.name] = series, data
            print(f"done {case.name} ({time.perf_counter() - total:.0f} s)", flush=True)
        if cases:  # the quick preset must not overwrite the README's figures
            figure(group, cases, all_series, all_data, OUT if quick else FIGURES)
    unc = (uncertainty(UNCERTAINTY_STDS[1::2] if quick else UNCERTAINTY_STDS, seed)
           if set(only) == set(GROUPS) else [])
    print(table(results))
    print()
    print(summary(results))
    print("\n| true coefficient std | across samples | around smooth mean | from residuals | "
          "std of (mean - truth) |\n|---|---|---|---|---|")
    for u in unc:
        print(f"| {u['true_std']} | {u['across_samples']:.4f} | "
              f"{u['around_smooth_mean']:.4f} | {u['from_residuals']:.4f} | "
              f"{u['residual_std']:.4f} |")
    print(f"\ntotal wall time {time.perf_counter() - total:.0f} s; figures in "
          f"{OUT if quick else FIGURES}, raw numbers in {OUT / 'paper_suite.json'}")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "paper_suite.json").write_text(json.dumps(
        {"cases": results, "uncertainty": unc}, indent=1, default=float))
    return results, unc


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--groups", nargs="+", choices=GROUPS, default=list(GROUPS),
                        help="run these groups of cases only (figures go to "
                             "benchmarks/output/)")
    args = parser.parse_args()
    from _runner import environment  # noqa: E402

    print(environment(), flush=True)  # what the numbers depend on, first
    main(args.quick, args.seed, tuple(args.groups))
