"""Tutorial: a switching bistable model of a worm's brain (the seed paper's C. elegans case).
==========================================================================================

The first principal component x of whole-brain calcium imaging is modelled as
``xdot = y``, ``ydot = a x^3 + b x^2 + c x + d y + u(t)`` with only u varying (dynamic
SINDy), u is turned into a two-level switch, the constants are refitted under it, and
the model is integrated under the switch and compared with the data. The fixed points
of each level show the bistability.

Without a path this writes a synthetic worm (the paper's coefficients, 100 noisy
neurons, 2.8 Hz, 3000 frames) in the file layout you choose, reads it back and compares
what it finds with the truth. With the real data (Kato et al. 2015, not downloaded
here):

    python examples/c_elegans.py --data path/to/WT_NoStim.mat       # v7.3, all worms
    python examples/c_elegans.py --data path/to/wbdata/              # per-worm v5 files
    python examples/c_elegans.py --data path/to/wbdata/TS2014..._basal_1080s.mat

Run:  python examples/c_elegans.py [--layout v5|v7.3]   (figure in examples/output/)
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

from latentsindy import celegans

OUTPUT = Path(__file__).resolve().parent / "output"  # beside this script, from any folder

MARGIN_FRAMES = 5  # a switch in the last frames leaves no trace in the data


def observable(true, t):
    """True switches with at least MARGIN_FRAMES frames after them."""
    true = np.asarray(true)
    return true[true < t[-MARGIN_FRAMES]]


def switch_time_error(found, true, t):
    """Largest distance from an observable true switch to the nearest found one."""
    true = observable(true, t)
    if found.size == 0:
        return np.inf
    return float(max(np.min(np.abs(found - s)) for s in true)) if true.size else 0.0


def main(layout="v5", data=None, n_frames=3000, n_worms=1, stage_one=True, training=None,
         output=OUTPUT, seed=0):
    truths = None
    if data is None:
        pairs = [celegans.switching_worm(n_frames=n_frames, seed=seed + i,
                                         name=f"synthetic_worm_{i}") for i in range(n_worms)]
        recordings, truths = [p[0] for p in pairs], [p[1] for p in pairs]
        if layout not in ("v5", "v7.3"):
            raise ValueError(f"layout must be 'v5' or 'v7.3'; got {layout!r}.")
        with tempfile.TemporaryDirectory(prefix="latentsindy_worms_") as tmp:
            folder = Path(tmp)
            if layout == "v5":
                data = folder / "wbdata"
                celegans.write_kato_folder(data, recordings)
            else:
                data = celegans.write_wt_nostim(folder / "WT_NoStim.mat", recordings)
            print(f"synthetic worm(s) written in the {layout} layout to a temporary {data}")
            recordings = celegans.load_kato(data)  # read back; the files go afterwards
    else:
        recordings = celegans.load_kato(data)
    for rec in recordings:
        print(f"{rec.name}: {rec.traces.shape[1]} neurons, {rec.t.size} frames at "
              f"{rec.fps:.2f} Hz")
    model = celegans.fit_switching_model(recordings, stage_one=stage_one, training=training,
                                         seed=seed)
    print(model.summary())
    report = {"model": model, "recordings": recordings, "truths": truths}
    if truths is not None:
        truth = truths[0]
        errors = {k: abs(model.cubic[k] / v - 1) for k, v in truth.cubic.items()}
        stage = {k: abs(model.stage_one_cubic[0][k] / v - 1) for k, v in truth.cubic.items()}
        print("truth: ydot = " + " ".join(f"{v:+.4g}*{k}" for k, v in truth.cubic.items())
              + f" + u, u in {truth.levels}")
        print("coefficient errors: " + ", ".join(f"{k} {v:.1%}" for k, v in errors.items()))
        if stage_one:
            print("stage one alone (free u): "
                  + ", ".join(f"{k} {v:.0%}" for k, v in stage.items()))
        for w, tr in zip(model.worms, truths, strict=True):
            err = switch_time_error(w.switch.switch_times, tr.switch_times, w.t)
            crossings = np.flatnonzero(np.diff(w.sigmoid_u > np.mean(w.raw_u))).size
            print(f"{w.name}: {w.switch.switch_times.size} switches found, "
                  f"{observable(tr.switch_times, w.t).size} true; worst switch-time error "
                  f"{err:.2f} s ({err / (w.t[-1] - w.t[0]):.2%} of the series); the paper's "
                  f"sigmoid recipe switches {crossings} times")
        report["coefficient_errors"] = errors
        report["switch_errors"] = [switch_time_error(w.switch.switch_times, tr.switch_times,
                                                     w.t) / (w.t[-1] - w.t[0])
                                   for w, tr in zip(model.worms, truths, strict=True)]
    if output:
        path = Path(output) / ("c_elegans.png" if truths is None
                               else f"c_elegans_{layout.replace('.', '')}.png")
        path.parent.mkdir(parents=True, exist_ok=True)
        fig = model.plot(path, truth=truths[0] if truths else None)
        import matplotlib.pyplot as plt

        plt.close(fig)
        report["figure"] = path
        print(f"figure: {path}")
    return report


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", help="WT_NoStim.mat, a wbdata/ folder or one worm's file")
    parser.add_argument("--layout", choices=["v5", "v7.3"], default="v5",
                        help="layout of the synthetic file when --data is not given")
    parser.add_argument("--worms", type=int, default=1, help="synthetic worms (shared cubic)")
    args = parser.parse_args()
    main(args.layout, args.data, n_worms=args.worms)
