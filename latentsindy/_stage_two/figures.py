"""The figure of a discovery: observed data against the closed system, hidden states
with their band."""

from __future__ import annotations

import numpy as np

from .._core.figures import BAND, finish, pyplot, truth_array


def plot_discovery(result, truth=None, *, simulation=None, figsize=None, path=None):
    """Observed data against the closed system, hidden states with their band.

    One panel per observed state (data as dots, the closed system's simulation from
    the fitted initial state as a line) and per hidden state (the reported series with
    a band of +- 2 standard deviations; with ``truth``, the true hidden variables mapped
    affinely into each hidden state's units, dashed). The title says whether the result
    is confident.
    """
    plt = pyplot()
    n_obs, n_hid = len(result.observed_names), len(result.hidden_names)
    sim = result.simulate() if simulation is None else simulation
    fig, axes = plt.subplots(n_obs + n_hid, 1, sharex=True, squeeze=False,
                             figsize=figsize or (9.0, 2.2 * (n_obs + n_hid) + 0.6))
    axes = axes[:, 0]
    t = result.times
    for i, name in enumerate(result.observed_names):
        ax = axes[i]
        ax.plot(t, result.observed[:, i], ".", ms=2, color="0.55", label="data")
        ax.plot(sim.t, sim.x[:, i], color="C0", lw=1.5, label=f"closed system ({sim.status})")
        ax.set_ylabel(name)
        ax.legend(loc="upper right", fontsize=8)
    mapped = None
    if truth is not None:
        true = truth_array(truth, len(t), "truth")
        design = np.column_stack([true, np.ones(len(t))])
        coef, *_ = np.linalg.lstsq(design, result.hidden, rcond=None)
        mapped = design @ coef  # each hidden state predicted from the truth, affinely
    for a, name in enumerate(result.hidden_names):
        ax = axes[n_obs + a]
        h, s = result.hidden[:, a], result.hidden_std[:, a]
        ax.plot(t, h, color="C1", lw=1.5, label=f"{name} (fitted)")
        if np.all(np.isfinite(s)):
            ax.fill_between(t, h - BAND * s, h + BAND * s, color="C1", alpha=0.25, lw=0,
                            label=f"+- {BAND:g} std")
        if mapped is not None:
            ax.plot(t, mapped[:, a], "k--", lw=1, label="truth (affine map)")
        ax.set_ylabel(name)
        ax.legend(loc="upper right", fontsize=8)
    axes[-1].set_xlabel("t")
    verdict = ("confident" if result.confident
               else "NOT confident: see summary() for doubts and alternatives")
    fig.suptitle(f"{n_obs} observed + {n_hid} hidden state(s); {verdict}", fontsize=10)
    return finish(fig, path)
