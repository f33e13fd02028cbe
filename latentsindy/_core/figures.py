"""What every figure shares: matplotlib on demand (an optional extra, ``pip install
"latentsindy[plot]"``), checked truth arrays, and saving in one place."""

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


def truth_array(truth, n_times, what):
    arr = np.asarray(truth, dtype=float)
    arr = arr[:, None] if arr.ndim == 1 else arr
    if arr.ndim != 2 or arr.shape[0] != n_times:
        raise ValueError(f"{what} must have shape (n_times,) or (n_times, n_true) with "
                         f"n_times = {n_times}; got shape {np.shape(truth)}.")
    return arr


def finish(fig, path):
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
