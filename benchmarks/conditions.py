"""Conditions benchmark: discovery on data as measured, next to the same draws sampled
uniformly.

For each family and draw (``_families.py``, the discovery benchmark's parameters) and
noise level, ``discover_hidden`` at default settings on the same system under:

* ``uniform``: 2000 equally spaced samples (the reference);
* ``jittered``: every sample time moved by up to 0.3 of the step;
* ``random``: 2000 sorted uniformly random times;
* ``two rates``: the first half of the time span sampled four times as densely as the
  second (1600 and 400 samples);
* ``gaps``: the uniform recording with one long stretch of NaN rows and one long
  stretch not recorded at all (a jump in time), each 6% of the samples, and five short
  runs of 1-4 NaN rows;
* ``short``: 3-5 recordings of 200-400 samples each, cut from one run at different
  places, every one at its own rate (every 1st, 2nd or 3rd sample).

Scored as in the discovery benchmark (``_scoring.py``), with R^2 of the true hidden
variables over every segment used, and "wrong yet confident": a wrong structure
reported with ``result.confident``. "error vs uniform" is the median hidden-equation
error over the draws under the condition divided by the same draws' median uniformly
sampled.

Usage::

    python benchmarks/conditions.py                  # 3 families, 10 draws, 1% and 5%
    python benchmarks/conditions.py --quick          # 2 draws at 1%
    python benchmarks/conditions.py --jobs 14 --out rows.json
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _families import FAMILIES, draw  # noqa: E402
from _runner import run_all  # noqa: E402
from _scoring import score_structure  # noqa: E402

from latentsindy import discover_hidden  # noqa: E402

CONDITIONS = ("uniform", "jittered", "random", "two rates", "gaps", "short")
DEFAULT_FAMILIES = ("lotka_volterra", "oscillator_logistic", "fitzhugh_nagumo")
N = 2000


def _rng(condition, index):
    return np.random.default_rng([CONDITIONS.index(condition), index, 77])


def _sampling(condition, index):
    """``t_end -> times`` for the single-recording conditions (None: uniform)."""
    if condition == "jittered":
        def times(t_end):
            dt = t_end / (N - 1)
            shift = _rng(condition, index).uniform(-0.3, 0.3, N) * dt
            shift[0], shift[-1] = 0.0, 0.0
            return np.linspace(0.0, t_end, N) + shift
        return times
    if condition == "random":
        def times(t_end):
            inner = np.sort(_rng(condition, index).uniform(0.0, t_end, N - 2))
            return np.concatenate([[0.0], inner, [t_end]])
        return times
    if condition == "two rates":
        def times(t_end):
            dense = np.linspace(0.0, t_end / 2, 1600, endpoint=False)
            return np.concatenate([dense, np.linspace(t_end / 2, t_end, 400)])
        return times
    return None


def recordings(family, index, noise, condition):
    """(x, t, truth) lists: what discover_hidden is given and the true hidden series."""
    d = draw(family, index, noise, _sampling(condition, index))
    x, t, h = d.observed.copy(), d.t.copy(), d.hidden_true
    if condition == "gaps":
        rng = _rng(condition, index)
        long = int(0.06 * N)
        a, b = np.sort(rng.choice(np.arange(100, N - 100 - 2 * long), 2, replace=False))
        b = max(b, a + long + 100)
        x[a:a + long] = np.nan  # missing rows
        for start in rng.choice(np.arange(50, N - 50), 5, replace=False):
            x[start:start + rng.integers(1, 5)] = np.nan
        keep = np.ones(N, dtype=bool)
        keep[b:b + long] = False  # not recorded: a jump in time
        return [x[keep]], [t[keep]], [h[keep]], d
    if condition == "short":
        rng = _rng(condition, index)
        n_rec = int(rng.integers(3, 6))
        lengths = rng.integers(200, 401, n_rec)
        strides = rng.integers(1, 4, n_rec)
        while np.sum(lengths * strides) > N:  # fit them into one run, disjoint
            strides[np.argmax(strides)] -= 1
        slack = N - int(np.sum(lengths * strides))
        spaces = np.diff(np.sort(rng.integers(0, slack + 1, n_rec)), prepend=0)
        xs, ts, hs, start = [], [], [], 0
        for length, stride, space in zip(lengths, strides, spaces, strict=True):
            start += int(space)
            rows = start + stride * np.arange(length)
            xs.append(x[rows])
            ts.append(t[rows])
            hs.append(h[rows])
            start = int(rows[-1]) + 1
        return xs, ts, hs, d
    return [x], [t], [h], d


def _r2_all(result, truths, kept):
    """R^2 of every true hidden variable from the hidden series of every segment used
    (one affine map for all segments: they share the hidden states' definitions); the
    smallest over the true hidden variables."""
    hidden, truth = [], []
    for k, (rec, first, last) in enumerate(result.data_use.sources):
        rows = kept[rec][(kept[rec] >= first) & (kept[rec] <= last)]
        hidden.append(result.all_hidden[k])
        truth.append(truths[rec][rows])
    hidden, truth = np.vstack(hidden), np.vstack(truth)
    design = np.column_stack([hidden, np.ones(len(hidden))])
    coef, *_ = np.linalg.lstsq(design, truth, rcond=None)
    resid = truth - design @ coef
    r2 = 1 - np.sum(resid**2, axis=0) / np.sum((truth - truth.mean(axis=0)) ** 2, axis=0)
    return float(np.min(r2))


def run_one(family, index, noise, condition):
    xs, ts, hs, d = recordings(family, index, noise, condition)
    kept = [np.flatnonzero(np.all(np.isfinite(x), axis=1)) for x in xs]
    row = {"family": family, "draw": index, "noise": noise, "condition": condition,
           "samples": int(sum(len(x) for x in xs)), "recordings": len(xs)}
    start = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = discover_hidden(xs if len(xs) > 1 else xs[0],
                                     FAMILIES[family].library(),
                                     t=ts if len(ts) > 1 else ts[0],
                                     feature_names=list(d.observed_names), verbose=False)
        row["wall"] = time.perf_counter() - start
        row.update(score_structure(result, d))
        row.update(r2=_r2_all(result, hs, kept), confident=result.confident,
                   segments=result.data_use.segments, summary=result.summary())
    except Exception as err:  # noqa: BLE001 - a failure is a benchmark outcome
        row.update(wall=time.perf_counter() - start, failed=f"{type(err).__name__}: {err}",
                   exact=False, confident=False, error=np.inf, r2=np.nan, n_hidden=0,
                   n_hidden_true=len(d.truth["hidden"]))
    return row


def _pct(v):
    return "inf" if not np.isfinite(v) else f"{100 * v:.2f}%"


def table(rows):
    lines = ["| family | noise | condition | draws | hidden states right | exact structure | "
             "hidden R^2 median / worst | hidden-eq. error median / worst | error vs uniform | "
             "wrong yet confident | wall median / max (s) |", "|---" * 11 + "|"]
    keys = sorted({(r["family"], r["noise"], r["condition"]) for r in rows},
                  key=lambda k: (list(FAMILIES).index(k[0]), k[1], CONDITIONS.index(k[2])))
    for fam, noise, cond in keys:
        rs = [r for r in rows if (r["family"], r["noise"], r["condition"]) == (fam, noise, cond)]
        ref = {r["draw"]: r["error"] for r in rows
               if (r["family"], r["noise"], r["condition"]) == (fam, noise, "uniform")}
        n = len(rs)
        right = sum(r["n_hidden"] == r["n_hidden_true"] for r in rs)
        exact = sum(bool(r["exact"]) for r in rs)
        r2 = np.array([r["r2"] for r in rs], dtype=float)
        err = np.array([r["error"] for r in rs], dtype=float)
        base = [ref[r["draw"]] for r in rs if r["draw"] in ref]
        ratio = (f"{np.median(err) / np.median(base):.2f}x"
                 if base and np.isfinite(np.median(base)) and np.median(base) > 0 else "-")
        wrong = sum(not r["exact"] and r["confident"] for r in rs)
        walls = [r["wall"] for r in rs]
        lines.append(
            f"| {fam} | {noise:.0%} | {cond} | {n} | {right}/{n} | {exact}/{n} | "
            f"{np.nanmedian(r2):.4f} / {np.nanmin(r2):.4f} | {_pct(np.median(err))} / "
            f"{_pct(np.max(err))} | {ratio} | {wrong}/{n} | {np.median(walls):.1f} / "
            f"{np.max(walls):.1f} |")
    return "\n".join(lines)


def main(families=DEFAULT_FAMILIES, draws=10, noise=(0.01, 0.05), conditions=CONDITIONS,
         jobs=1, out=None):
    tasks = [(f, k, nz, c) for f in families for nz in noise for c in conditions
             for k in range(draws)]

    def report(row):
        print(f"{row['family']:20s} {row['noise']:.0%} {row['condition']:10s} draw "
              f"{row['draw']}: hidden {row['n_hidden']}/{row['n_hidden_true']} exact "
              f"{row['exact']} confident {row['confident']} error {_pct(row['error'])} "
              f"R^2 {row['r2']:.4f} ({row['wall']:.1f} s)"
              + (f" FAILED {row['failed']}" if "failed" in row else ""), flush=True)

    rows = run_all(run_one, tasks, report, jobs, out)
    print()
    print(table(rows))
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 draws at 1%% noise")
    parser.add_argument("--families", nargs="+", choices=list(FAMILIES),
                        default=list(DEFAULT_FAMILIES))
    parser.add_argument("--conditions", nargs="+", choices=CONDITIONS, default=list(CONDITIONS))
    parser.add_argument("--draws", type=int, default=10)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.01, 0.05])
    parser.add_argument("--jobs", type=int, default=1, help="processes (one thread each)")
    parser.add_argument("--out", help="write every row as JSON here")
    args = parser.parse_args()
    from _runner import environment  # noqa: E402

    print(environment(), flush=True)  # what the numbers depend on, first
    if args.quick:
        args.draws, args.noise = 2, [0.01]
    main(args.families, args.draws, tuple(args.noise), tuple(args.conditions), args.jobs,
         args.out)
