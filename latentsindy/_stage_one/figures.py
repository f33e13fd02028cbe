"""The figure of stage one's coefficients: each over time with its band and switch times."""

from __future__ import annotations

import numpy as np

from .._core.figures import finish, pyplot, truth_array


def plot_coefficients(series, truth=None, *, terms=None, figsize=None, path=None):
    """Coefficients over time with their uncertainty band (``series.lower/upper``).

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
        m = series.term(state, feature)
        lo, hi = series.term_band(state, feature)
        ax.plot(t, m, color="C0", lw=1.5, label="posterior mean")
        ax.fill_between(t, lo, hi, color="C0", alpha=0.25, lw=0, label="band (95%)")
        if (state, feature) in truth:
            ax.plot(t, truth_array(truth[(state, feature)], len(t), "truth")[:, 0], "k--",
                    lw=1, label="truth")
        for k, ts in enumerate(switches):
            ax.axvline(ts, color="C3", lw=0.8, ls=":", label="switch" if k == 0 else None)
        ax.set_ylabel(f"d{state}/dt: {feature}", fontsize=8)
        ax.legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("t")
    if series.doubts:
        fig.suptitle("NOT CONFIDENT: " + "; ".join(series.doubts)[:300], fontsize=7,
                     color="C3", wrap=True)
    return finish(fig, path)
