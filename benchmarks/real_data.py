"""Real-data benchmark: recordings as scientists have them, at default settings.

Two parts:

* **Real series** (``benchmarks/data``, sources in its README):
  - hare-lynx pelts 1900-1920, the hare observed and the lynx hidden: R^2 of the lynx
    from the hidden state (best affine map), and a forecast of the last 5 years from
    the state fitted at 1915 (fitted on 1900-1915), against an AR(2) model fitted to
    the same years (RMSE in thousands of pelts);
  - indomethacin, 6 subjects of 11 samples: the law found, and leave-one-subject-out
    prediction (the law fitted on five subjects; the sixth's hidden start fitted to its
    first three samples, its other eight predicted; RMSE relative to their spread).
* **Real-noise conditions** on families of ``_families.py`` (10 draws each by default),
  each next to nothing: the draw's noise-free observed series with
  - ``ar1 0.5`` / ``ar1 0.9``: AR(1) noise (correlation phi between samples), 2% of each
    state's std;
  - ``outliers 0.5%`` / ``outliers 2%``: 1% white noise plus that share of samples hit
    by spikes of 10 noise levels (a loose connector);
  - ``poisson``: counts, Poisson with a mean of 400 at the state's mean level (positive
    families only);
  - ``8/cycle``, ``12/cycle``, ``16/cycle``: 1% noise, sampled that many times per
    cycle of the fastest oscillation (the draw's dominant period), over its time span;
  - ``panel 10x11`` / ``panel 20x11``: 10 or 20 recordings of 11 irregular samples each
    (1% noise), cut from one run at different places, each spanning about one cycle.

Columns as in the discovery table, plus "wrong yet confident" (a wrong structure
reported with ``confident``) and "right but flagged" (the exact structure, not
confident). A call that raises is counted as refused.

Usage::

    python benchmarks/real_data.py                 # everything, 10 draws
    python benchmarks/real_data.py --quick         # real series and 2 draws per condition
    python benchmarks/real_data.py --part series   # the real series only
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pysindy as ps

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _families import FAMILIES, draw  # noqa: E402
from _runner import run_all  # noqa: E402
from _scoring import score_structure  # noqa: E402

from latentsindy import discover_hidden  # noqa: E402
from latentsindy._core.oscillation import crossing_periods  # noqa: E402

DATA = Path(__file__).resolve().parent / "data"
CONDITIONS = ("ar1 0.5", "ar1 0.9", "outliers 0.5%", "outliers 2%", "poisson", "8/cycle",
              "12/cycle", "16/cycle", "panel 10x11", "panel 20x11")
DEFAULT_FAMILIES = ("lotka_volterra", "oscillator_logistic", "epidemic")
POSITIVE = ("lotka_volterra", "epidemic")  # families whose observed states are counts
MEAN_COUNT = 400.0


def _quiet(call):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return call()


def _rng(condition, index):
    return np.random.default_rng([CONDITIONS.index(condition), index, 56])


def _period(t, x):
    """The shortest crossing period over the states (the fastest oscillation); the span
    when nothing oscillates."""
    return min(crossing_periods(x, t), default=t[-1] - t[0])


def recordings(family, index, condition):
    """(x list, t list, kept rows list, draw) for one condition."""
    base = draw(family, index, 0.0)
    clean, std = base.observed_clean, base.observed_clean.std(axis=0)
    rng = _rng(condition, index)
    if condition.startswith("ar1"):
        phi = float(condition.split()[1])
        e = rng.standard_normal(clean.shape) * np.sqrt(1 - phi**2)
        noise = np.zeros_like(clean)
        noise[0] = rng.standard_normal(clean.shape[1])
        for k in range(1, len(clean)):
            noise[k] = phi * noise[k - 1] + e[k]
        return [clean + 0.02 * std * noise], [base.t], base
    if condition.startswith("outliers"):
        share = float(condition.split()[1].rstrip("%")) / 100
        x = clean + 0.01 * std * rng.standard_normal(clean.shape)
        hit = rng.choice(len(x), max(1, round(share * len(x))), replace=False)
        x[hit] += 10 * 0.01 * std * rng.choice([-1.0, 1.0], (len(hit), clean.shape[1]))
        return [x], [base.t], base
    if condition == "poisson":
        scale = MEAN_COUNT / np.maximum(clean.mean(axis=0), 1e-300)
        return [rng.poisson(np.maximum(clean, 0) * scale) / scale], [base.t], base
    if condition.endswith("/cycle"):
        per = int(condition.split("/")[0])
        period = _period(base.t, clean)
        n = max(int(round((base.t[-1] - base.t[0]) / period * per)) + 1, 8)
        d = draw(family, index, 0.01, lambda t_end: np.linspace(0.0, t_end, n))
        return [d.observed], [d.t], d
    if condition.startswith("panel"):
        n_rec = int(condition.split()[1].split("x")[0])
        period = _period(base.t, clean)
        # about one cycle each (a third of the run at most: one wave is a whole run)
        span = min(max(11, int(round(period / (base.t[1] - base.t[0])))), len(clean) // 3)
        x = clean + 0.01 * std * rng.standard_normal(clean.shape)
        starts = np.sort(rng.choice(len(x) - span - 1, n_rec, replace=False))
        rows = [s + np.sort(rng.choice(span, 11, replace=False)) for s in starts]
        return [x[r] for r in rows], [base.t[r] for r in rows], base
    raise ValueError(condition)


def run_condition(family, index, condition):
    row = {"part": "condition", "family": family, "draw": index, "condition": condition}
    if condition == "poisson" and family not in POSITIVE:
        return row | {"skipped": True}
    xs, ts, d = recordings(family, index, condition)
    row["samples"] = int(sum(len(x) for x in xs))
    start = time.perf_counter()
    try:
        result = _quiet(lambda: discover_hidden(
            xs if len(xs) > 1 else xs[0], FAMILIES[family].library(),
            t=ts if len(ts) > 1 else ts[0], feature_names=list(d.observed_names),
            verbose=False))
        row.update(score_structure(result, d))
        row.update(confident=result.confident, hidden_found=len(result.hidden_names),
                   summary=result.summary())
    except Exception as err:  # noqa: BLE001 - a refusal is a benchmark outcome
        row.update(refused=f"{type(err).__name__}: {err}", exact=False, confident=False,
                   error=np.inf, n_hidden=0, n_hidden_true=len(d.truth["hidden"]))
    row["wall"] = time.perf_counter() - start
    return row


def _hare_lynx():
    table = np.genfromtxt(DATA / "hare_lynx_1900_1920.csv", delimiter=",", names=True)
    return table["year"], table["hare"], table["lynx"]


def _ar2_forecast(y, steps):
    """AR(2) with a constant fitted by least squares; iterated forecasts."""
    design = np.column_stack([y[1:-1], y[:-2], np.ones(len(y) - 2)])
    coef, *_ = np.linalg.lstsq(design, y[2:], rcond=None)
    out = list(y[-2:])
    for _ in range(steps):
        out.append(coef[0] * out[-1] + coef[1] * out[-2] + coef[2])
    return np.array(out[2:])


def run_hare_lynx():
    year, hare, lynx = _hare_lynx()
    row = {"part": "series", "series": "hare-lynx 1900-1920 (lynx hidden)"}
    library = ps.PolynomialLibrary(degree=2)
    start = time.perf_counter()
    try:
        whole = _quiet(lambda: discover_hidden(hare[:, None], library, t=year,
                                               feature_names=["hare"], verbose=False))
        r2 = (float(whole.compare_hidden(lynx).r2.min()) if whole.hidden_names
              else float("nan"))
        row.update(answer=repr(whole), confident=whole.confident, r2=r2,
                   doubts=[d.kind for d in whole.doubts], summary=whole.summary())
    except Exception as err:  # noqa: BLE001
        row.update(refused=f"{type(err).__name__}: {err}")
    cut = 16
    try:
        part = _quiet(lambda: discover_hidden(hare[:cut, None], library, t=year[:cut],
                                              feature_names=["hare"], verbose=False))
        # the state at the cut: the hare as counted, the hidden states as fitted
        x0 = np.concatenate([hare[cut - 1:cut], part.hidden[-1]])
        sim = part.simulate(year[cut - 1:], x0=x0)
        forecast = sim.x[1:, 0] if sim.status == "success" else np.full(5, np.nan)
        row["forecast_rmse"] = float(np.sqrt(np.mean((forecast - hare[cut:]) ** 2)))
    except Exception as err:  # noqa: BLE001
        row["forecast_refused"] = f"{type(err).__name__}: {err}"
    row["ar2_rmse"] = float(np.sqrt(np.mean((_ar2_forecast(hare[:cut], 5) - hare[cut:]) ** 2)))
    row["wall"] = time.perf_counter() - start
    return row


def _indomethacin():
    table = np.genfromtxt(DATA / "indomethacin.csv", delimiter=",", names=True)
    subjects = np.unique(table["subject"])
    return [(table["time_h"][table["subject"] == s], table["conc_mcg_ml"][table["subject"] == s])
            for s in subjects]


def run_indomethacin():
    subjects = _indomethacin()
    row = {"part": "series", "series": "indomethacin, 6 subjects x 11 samples"}
    library = ps.PolynomialLibrary(degree=1)
    start = time.perf_counter()

    def fit(which):
        return _quiet(lambda: discover_hidden([subjects[k][1][:, None] for k in which],
                                              library, t=[subjects[k][0] for k in which],
                                              feature_names=["C"], verbose=False))
    try:
        whole = fit(range(len(subjects)))
        row.update(answer=repr(whole), confident=whole.confident,
                   doubts=[d.kind for d in whole.doubts], summary=whole.summary())
    except Exception as err:  # noqa: BLE001
        row.update(refused=f"{type(err).__name__}: {err}")
    errors = []
    for out in range(len(subjects)):
        t, c = subjects[out]
        try:
            law = fit([k for k in range(len(subjects)) if k != out])
            errors.append(_loso_error(law, t, c))
        except Exception:  # noqa: BLE001
            errors.append(np.inf)
    row["loso_rmse_over_spread"] = errors
    row["wall"] = time.perf_counter() - start
    return row


def _loso_error(law, t, c):
    """The held-out subject's hidden start fitted to its first three samples (a grid
    over the training subjects' hidden range), the rest predicted."""
    n_hidden = len(law.hidden_names)
    starts = [np.array([c[0]])]
    if n_hidden:
        lo = min(float(np.min(h)) for h in law.all_hidden)
        hi = max(float(np.max(h)) for h in law.all_hidden)
        grid = np.linspace(lo, hi, 41)
        starts = [np.concatenate([[c[0]], [g] + [0.0] * (n_hidden - 1)]) for g in grid]
    best, err = np.inf, np.inf
    for x0 in starts:
        sim = law.simulate(t, x0=x0)
        if sim.status != "success":
            continue
        fit3 = float(np.mean((sim.states[:3, 0] - c[:3]) ** 2))
        if fit3 < best:
            best = fit3
            err = float(np.sqrt(np.mean((sim.states[3:, 0] - c[3:]) ** 2)) / np.std(c[3:]))
    return err


def condition_table(rows):
    lines = ["| family | condition | draws | samples | hidden states right | exact | "
             "hidden-eq. error median | wrong yet confident | right but flagged | refused | "
             "wall median / max (s) |", "|---" * 11 + "|"]
    rows = [r for r in rows if r.get("part") == "condition" and not r.get("skipped")]
    keys = sorted({(r["family"], r["condition"]) for r in rows},
                  key=lambda k: (list(FAMILIES).index(k[0]), CONDITIONS.index(k[1])))
    for fam, cond in keys:
        rs = [r for r in rows if (r["family"], r["condition"]) == (fam, cond)]
        n = len(rs)
        right = sum(r["n_hidden"] == r["n_hidden_true"] for r in rs)
        exact = sum(bool(r["exact"]) for r in rs)
        wrong = sum(not r["exact"] and r["confident"] for r in rs)
        flagged = sum(bool(r["exact"]) and not r["confident"] for r in rs)
        refused = sum("refused" in r for r in rs)
        err = np.median([r["error"] for r in rs])
        walls = [r["wall"] for r in rs]
        lines.append(f"| {fam} | {cond} | {n} | {int(np.median([r['samples'] for r in rs]))} "
                     f"| {right}/{n} | {exact}/{n} | "
                     f"{'inf' if not np.isfinite(err) else f'{100 * err:.2f}%'} | {wrong}/{n} "
                     f"| {flagged}/{n} | {refused}/{n} | {np.median(walls):.1f} / "
                     f"{np.max(walls):.1f} |")
    return "\n".join(lines)


def series_lines(rows):
    out = []
    for r in rows:
        if r.get("part") != "series":
            continue
        out.append(f"* {r['series']}: "
                   + (f"refused ({r['refused']})" if "refused" in r else
                      f"{r['answer']}, doubts {r['doubts']}")
                   + (f"; lynx R^2 {r['r2']:.2f}" if "r2" in r else "")
                   + (f"; 5-year forecast RMSE {r['forecast_rmse']:.1f} against AR(2) "
                      f"{r['ar2_rmse']:.1f}" if "forecast_rmse" in r else
                      f"; forecast refused, AR(2) RMSE {r['ar2_rmse']:.1f}"
                      if "ar2_rmse" in r else "")
                   + (f"; leave-one-subject-out RMSE / spread "
                      f"{np.round(r['loso_rmse_over_spread'], 2).tolist()}"
                      if "loso_rmse_over_spread" in r else "")
                   + f" ({r['wall']:.1f} s)")
    return "\n".join(out)


def main(part="all", families=DEFAULT_FAMILIES, draws=10, conditions=CONDITIONS, jobs=1,
         out=None):
    rows = []
    if part in ("all", "series"):
        for run in (run_hare_lynx, run_indomethacin):
            rows.append(run())
            print(series_lines(rows[-1:]), flush=True)
    if part in ("all", "conditions"):
        tasks = [(f, k, c) for f in families for c in conditions for k in range(draws)]

        def report(row):
            if row.get("skipped"):
                return
            print(f"{row['family']:20s} {row['condition']:14s} draw {row['draw']}: hidden "
                  f"{row['n_hidden']}/{row['n_hidden_true']} exact {row['exact']} confident "
                  f"{row['confident']} ({row['wall']:.1f} s)"
                  + (f" REFUSED {row['refused'][:120]}" if "refused" in row else ""),
                  flush=True)

        rows += run_all(run_condition, tasks, report, jobs, out)
    print()
    print(series_lines(rows))
    print()
    print(condition_table(rows))
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="the real series and 2 draws per condition")
    parser.add_argument("--part", choices=("all", "series", "conditions"), default="all")
    parser.add_argument("--families", nargs="+", choices=list(FAMILIES),
                        default=list(DEFAULT_FAMILIES))
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS,
                        default=list(CONDITIONS))
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--jobs", type=int, default=1, help="processes (one thread each)")
    parser.add_argument("--out", help="write every condition row as JSON here")
    args = parser.parse_args()
    from _runner import environment  # noqa: E402

    print(environment(), flush=True)  # what the numbers depend on, first
    if args.quick:
        args.draws = 2
    main(args.part, args.families, args.draws, tuple(args.conditions), args.jobs, args.out)
