"""How long one ``discover_hidden`` call takes, next to plain pysindy on the same data.

For each family and draw (``benchmarks/_families.py``, default settings, 1% noise) one
``discover_hidden`` call runs alone in this process (no other job beside it), then 20
pysindy SINDy fits (STLSQ, polynomials of degree 3) of the same system with every state
observed (the clean states plus 1% noise) are timed in the same run, three times, the
fastest kept (``pysindy_seconds``): the ratio says what
discovery costs in units of the plain regression a user would run if nothing were
hidden. Prints a row per call and the medians per family, and the stages' median split
(``result.timings``).

Usage::

    python benchmarks/speed.py                       # prey-only LV, 5 draws
    python benchmarks/speed.py --families lorenz_z modulated lorenz_x --draws 3
    python benchmarks/speed.py --one-process         # no second process for stage two
    python benchmarks/speed.py --scaling --draws 3   # 2,000 samples against 20,000
    python benchmarks/speed.py --normal-equations    # dense against blocks, by size
    python benchmarks/speed.py --families hindmarsh_rose --noise 0.05 --max-time 20

``--scaling`` times each draw twice: as drawn (2,000 samples) and over ten times its
span at the same sampling density (20,000 samples), and prints the ratio of the two
calls' times (the target: at most 3).

``--max-time`` gives every call that budget (``discover_hidden(max_time=...)``) and
prints how far past it each call returned (what is left to run once it is spent: the
fit in flight, stage one's training), whether the result carries the budget's doubt,
and whether its structure is exact (scored as ``discovery.py`` scores it).

``--normal-equations`` times one point of the refinement's Levenberg-Marquardt fits
(assembling J^T J and J^T r from one block of rows per segment and one per continuity
gap, then two damped solves, as at an accepted point) held densely and by blocks
(``ArrowMatrix``), for systems of increasing size: where the two cost the same is
where ``normal_equations.DENSE`` sits.

A lone call may give stage two's independent pieces (held-out folds, candidates after
their first fit) to a second process on a second core (``latentsindy._core.parallel``);
``--one-process`` switches that off, for the one-core figure.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pysindy as ps

sys.path.insert(0, str(Path(__file__).parent))

from _families import ALL_FAMILIES, draw  # noqa: E402
from _scoring import score_structure  # noqa: E402

from latentsindy import discover_hidden  # noqa: E402
from latentsindy._core import parallel  # noqa: E402

PYSINDY_FITS = 20
PYSINDY_REPEATS = 3  # the fits are timed this many times, the fastest kept


def pysindy_seconds(d, noise, seed=0, repeats=PYSINDY_REPEATS):
    """Wall seconds of ``PYSINDY_FITS`` SINDy fits with every state observed: the
    fastest of ``repeats`` runs. Timed once, right after a discovery, the fits ran up
    to 40% slower than on the next runs (prey-only LV, 2026-12-02: 0.16-0.21 s against
    0.12-0.13 s; not so after a call without the second process), which made the
    ratio look better than it is."""
    full = np.hstack([d.observed_clean, d.hidden_true])
    rng = np.random.default_rng(seed)
    noisy = full + noise * full.std(axis=0) * rng.standard_normal(full.shape)
    best = np.inf
    with warnings.catch_warnings():  # STLSQ's default threshold may empty an equation
        warnings.simplefilter("ignore")
        for _ in range(repeats):
            start = time.perf_counter()
            for _ in range(PYSINDY_FITS):
                ps.SINDy(optimizer=ps.STLSQ(),
                         feature_library=ps.PolynomialLibrary(degree=3)).fit(noisy, t=d.t)
            best = min(best, time.perf_counter() - start)
    return best


def one(family, index, noise, span=1, max_time=None):
    d = draw(family, index, noise) if span == 1 else draw(
        family, index, noise, lambda t_end: np.linspace(0.0, span * t_end, 2000 * span))
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = discover_hidden(d.observed, ALL_FAMILIES[family].library(), t=d.t,
                                 feature_names=list(d.observed_names), verbose=False,
                                 max_time=max_time)
    wall = time.perf_counter() - start
    fits = pysindy_seconds(d, noise)
    return {"family": family, "draw": index, "wall": wall, "pysindy": fits,
            "ratio": wall / fits, "timings": dict(result.timings),
            "confident": result.confident, "samples": len(d.t),
            "budget": any(doubt.kind == "time budget" for doubt in result.doubts),
            "exact": bool(score_structure(result, d)["exact"]) if max_time else None}


def median_split(rows):
    """The stages' median seconds over ``rows`` (``one``'s), largest first, as text."""
    stages = sorted({k for r in rows for k in r["timings"]})
    split = {k: float(np.median([r["timings"].get(k, 0.0) for r in rows])) for k in stages}
    return ", ".join(f"{k} {v:.1f}" for k, v in sorted(split.items(), key=lambda kv: -kv[1])
                     if v >= 0.1)


def scaling(families, draws, noise, span=10):
    """Each draw as drawn and over ``span`` times its span (same density): the two
    calls' times and their ratio."""
    rows = []
    for family in families:
        for index in range(draws):
            short, long = one(family, index, noise), one(family, index, noise, span)
            rows.append((family, index, short, long))
            print(f"{family:20s} draw {index}: {short['samples']} samples {short['wall']:5.1f} s,"
                  f" {long['samples']} samples {long['wall']:5.1f} s, ratio "
                  f"{long['wall'] / short['wall']:.1f}", flush=True)
    print(f"\n| family | draws | median wall, 2,000 samples (s) | median wall, {2000 * span:,} "
          "samples (s) | median ratio | worst ratio | median split of the long call (s) |"
          "\n|---|---|---|---|---|---|---|")
    for family in families:
        rs = [r for r in rows if r[0] == family]
        ratios = [r[3]["wall"] / r[2]["wall"] for r in rs]
        text = median_split([r[3] for r in rs])
        print(f"| {family} | {len(rs)} | {np.median([r[2]['wall'] for r in rs]):.1f} | "
              f"{np.median([r[3]['wall'] for r in rs]):.1f} | {np.median(ratios):.1f} | "
              f"{max(ratios):.1f} | {text} |")
    return rows


# (free coefficients, segments, states): two-state systems of 10-40 segments, three-
# state ones of 40-100, four-state ones of 100
SHAPES = ((4, 10, 2), (6, 20, 2), (6, 40, 2), (10, 40, 3), (15, 60, 3), (20, 100, 3),
          (30, 100, 4))


def normal_equations(shapes=SHAPES, repeats=200, rows=20):
    """Milliseconds of assembly and of two damped solves, densely and by blocks, on
    one thread (as a discovery runs)."""
    from threadpoolctl import threadpool_limits

    from latentsindy._stage_two.fit import normal_equations as ne

    def point(p, k, n, dense):
        rng = np.random.default_rng(0)
        pairs = np.stack([np.arange(k - 1), np.arange(1, k)], axis=1)
        blocks = [(rng.normal(size=(k, rows, p + n)), rng.normal(size=(k, rows)),
                   np.arange(k)[:, None]),
                  (rng.normal(size=(k - 1, n, p + 2 * n)), rng.normal(size=(k - 1, n)), pairs)]
        saved, ne.DENSE = ne.DENSE, (10**9 if dense else 0)
        try:
            start = time.perf_counter()
            for _ in range(repeats):
                eq = ne.NormalEquations(p, k, n)
                for block in blocks:
                    eq.add(*block)
                matrix = eq.matrix()
            built = time.perf_counter()
            for _ in range(repeats):
                scale = matrix.diagonal()
                ne.solve(matrix, -eq.grad, 1e-10 * scale)
                step = ne.solve(matrix, -eq.grad, 1e-3 * scale)
            solved = time.perf_counter()
        finally:
            ne.DENSE = saved
        return (built - start) / repeats * 1e3, (solved - built) / repeats * 1e3, step

    print("| free coefficients | segments | states | unknowns | dense: assembly / two "
          "solves (ms) | blocks: assembly / two solves (ms) | largest difference |\n"
          "|---|---|---|---|---|---|---|")
    out = []
    for p, k, n in shapes:
        with threadpool_limits(1):
            dense, blocks = point(p, k, n, True), point(p, k, n, False)
        gap = float(np.max(np.abs(dense[2] - blocks[2])) / np.max(np.abs(dense[2])))
        print(f"| {p} | {k} | {n} | {p + k * n} | {dense[0]:.3f} / {dense[1]:.3f} | "
              f"{blocks[0]:.3f} / {blocks[1]:.3f} | {gap:.0e} |", flush=True)
        out.append((p, k, n, dense[:2], blocks[:2], gap))
    return out


def main(families, draws, noise, one_process=False, max_time=None):
    parallel.enable(not one_process)
    rows = []
    for family in families:
        for index in range(draws):
            row = one(family, index, noise, max_time=max_time)
            rows.append(row)
            print(f"{family:20s} draw {index}: {row['wall']:6.1f} s, {PYSINDY_FITS} pysindy "
                  f"fits {row['pysindy']:.3f} s, ratio {row['ratio']:.1f}" + (
                      "" if max_time is None else f", exact {row['exact']}, confident "
                      f"{row['confident']}, budget's doubt {row['budget']}"), flush=True)
    if max_time is not None:
        return budgeted(families, rows, max_time)
    print(f"\n| family | calls | median wall (s) | worst (s) | median {PYSINDY_FITS} pysindy "
          "fits (s) | median ratio | median split (s) |\n|---|---|---|---|---|---|---|")
    for family in families:
        rs = [r for r in rows if r["family"] == family]
        text = median_split(rs)
        print(f"| {family} | {len(rs)} | {np.median([r['wall'] for r in rs]):.1f} | "
              f"{max(r['wall'] for r in rs):.1f} | {np.median([r['pysindy'] for r in rs]):.3f} | "
              f"{np.median([r['ratio'] for r in rs]):.1f} | {text} |")
    return rows


def budgeted(families, rows, max_time):
    """The calls under ``max_time``: how far past it they returned, how many carry the
    budget's doubt."""
    print("\n| family | calls | budget (s) | median wall (s) | worst wall (s) | worst past "
          "the budget (s) | with the budget's doubt | exact structure | median split (s) |\n"
          "|---|---|---|---|---|---|---|---|---|")
    for family in families:
        rs = [r for r in rows if r["family"] == family]
        walls = [r["wall"] for r in rs]
        print(f"| {family} | {len(rs)} | {max_time:g} | {np.median(walls):.1f} | "
              f"{max(walls):.1f} | {max(walls) - max_time:.1f} | "
              f"{sum(r['budget'] for r in rs)} of {len(rs)} | "
              f"{sum(r['exact'] for r in rs)} of {len(rs)} | {median_split(rs)} |")
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", nargs="+", choices=list(ALL_FAMILIES),
                        default=["lotka_volterra"])
    parser.add_argument("--draws", type=int, default=5)
    parser.add_argument("--noise", type=float, default=0.01)
    parser.add_argument("--one-process", action="store_true",
                        help="no second process for stage two's independent pieces")
    parser.add_argument("--scaling", action="store_true",
                        help="each draw at 2,000 samples and over ten times its span")
    parser.add_argument("--max-time", type=float, default=None,
                        help="give every call this budget (seconds); report how far past it")
    parser.add_argument("--normal-equations", action="store_true",
                        help="the refinement's normal equations, dense against blocks")
    args = parser.parse_args()
    from _runner import environment  # noqa: E402

    print(environment(), flush=True)  # what the numbers depend on, first
    if args.normal_equations:
        normal_equations()
    elif args.scaling:
        parallel.enable(not args.one_process)
        scaling(args.families, args.draws, args.noise)
    else:
        main(args.families, args.draws, args.noise, args.one_process, args.max_time)
