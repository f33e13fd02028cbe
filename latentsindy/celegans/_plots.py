"""Figure of the switching model: data vs model, input and switch, phase portrait."""

from __future__ import annotations

import numpy as np

from .._core.figures import finish, pyplot
from ._dynamics import ORDER


def plot_model(model, *, path=None, truth=None, worm: int = 0):
    """Four panels for one worm: x from the data against the model integrated under the
    switch from the first frame; the raw input with the
    two-level switch (and the true switch times when ``truth`` has ``switch_times``);
    ``f(x) + u`` per level (ydot on the axis y = 0) with its fixed points (filled: stable);
    and the phase plane (x, y) of data and model.

    Returns the matplotlib figure; saved to ``path`` when given.
    """
    plt = pyplot()
    w = model.worms[worm]
    fig, axes = plt.subplots(2, 2, figsize=(12, 7))
    ax = axes[0, 0]
    ax.plot(w.t, w.x, ".", ms=2, color="0.5", label="data (first component)")
    ax.plot(w.t, w.free_run, lw=1.2, label=f"model from t0 (NRMSE {w.nrmse_free:.2f})")
    ax.set(xlabel="t (s)", ylabel="x", title=f"{w.name}: data and closed model")
    ax.legend(fontsize=7, loc="upper right")
    ax = axes[0, 1]
    ax.plot(w.t, w.raw_u, lw=0.8, color="0.6", label="stage-one u(t)")
    ax.plot(w.t, w.input_u, lw=0.8, label="u(t) through the final model")
    ax.plot(w.t, w.switch.values, lw=1.6, color="k", label="two-level switch")
    for i, s in enumerate(getattr(truth, "switch_times", ())):
        ax.axvline(s, color="r", lw=0.6, ls=":", label="true switch" if i == 0 else None)
    ax.set(xlabel="t (s)", ylabel="u", title="input")
    ax.legend(fontsize=7, loc="upper right")
    ax = axes[1, 0]
    span = np.linspace(w.x.min() - 1.0, w.x.max() + 1.0, 400)
    a, b, c, _ = (model.cubic[k] for k in ORDER)
    for level, points in w.fixed_points:
        line, = ax.plot(span, a * span**3 + b * span**2 + c * span + level,
                        label=f"u = {level:.3g}")
        for p in points:
            ax.plot(p.x, 0.0, "o", color=line.get_color(),
                    mfc=line.get_color() if p.stable else "white")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set(xlabel="x", ylabel="f(x) + u", title="fixed points (filled: stable)")
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    ax.plot(w.x, w.y, ".", ms=2, color="0.5", label="data")
    model_y = np.gradient(w.free_run, w.t)
    ax.plot(w.free_run, model_y, lw=0.8, label="model")
    ax.set(xlabel="x", ylabel="y = xdot", title="phase plane")
    ax.legend(fontsize=7)
    return finish(fig, path)
