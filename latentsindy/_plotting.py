"""Figures of results. matplotlib is an optional extra: ``pip install "latentsindy[plot]"``."""

from __future__ import annotations

import numpy as np

BAND = 2.0  # bands are mean +- BAND standard deviations


def pyplot():
    """matplotlib.pyplot, or an ImportError that names the extra to install."""
    try:
        import matplotlib.pyplot as plt
    except ImportError as err:
        raise ImportError(
            "Plotting needs matplotlib, an optional dependency of latentsindy; install it "
            'with pip install "latentsindy[plot]" (or pip install matplotlib).') from err
    return plt


def _truth_array(truth, n_times, what):
    arr = np.asarray(truth, dtype=float)
    arr = arr[:, None] if arr.ndim == 1 else arr
    if arr.ndim != 2 or arr.shape[0] != n_times:
        raise ValueError(f"{what} must have shape (n_times,) or (n_times, n_true) with "
                         f"n_times = {n_times}; got shape {np.shape(truth)}.")
    return arr


def _finish(fig, path):
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig


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
        true = _truth_array(truth, len(t), "truth")
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
    return _finish(fig, path)


def plot_coefficients(series, truth=None, *, terms=None, figsize=None, path=None):
    """Coefficients over time with bands of +- 2 posterior standard deviations.

    ``terms``: (state, feature) pairs (default every active one); ``truth``: a dict
    {(state, feature): array over ``series.times``} drawn dashed. Switch times
    (:meth:`CoefficientSeries.switch_times` on the varying terms) are marked.
    """
    plt = pyplot()
    terms = list(series.active_terms() if terms is None else terms)
    if not terms:
        raise ValueError("No coefficient to plot: the support is empty; pass terms=[...].")
    for pair in terms:
        series.term(*pair)  # refuses unknown names
    truth = dict(truth or {})
    varying = [p for p in terms if series.time_varying[series._state(p[0]),
                                                        series._feature(p[1])]]
    switches = series.switch_times(terms=varying) if varying else np.array([])
    fig, axes = plt.subplots(len(terms), 1, sharex=True, squeeze=False,
                             figsize=figsize or (9.0, 1.9 * len(terms) + 0.6))
    t = series.times
    for ax, (state, feature) in zip(axes[:, 0], terms, strict=True):
        m, s = series.term(state, feature), series.term_std(state, feature)
        ax.plot(t, m, color="C0", lw=1.5, label="posterior mean")
        ax.fill_between(t, m - BAND * s, m + BAND * s, color="C0", alpha=0.25, lw=0,
                        label=f"+- {BAND:g} std")
        if (state, feature) in truth:
            ax.plot(t, _truth_array(truth[(state, feature)], len(t), "truth")[:, 0], "k--",
                    lw=1, label="truth")
        for k, ts in enumerate(switches):
            ax.axvline(ts, color="C3", lw=0.8, ls=":", label="switch" if k == 0 else None)
        ax.set_ylabel(f"d{state}/dt: {feature}", fontsize=8)
        ax.legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("t")
    return _finish(fig, path)
