"""Input checks shared by the baselines."""

from __future__ import annotations

import numpy as np

from .._core import validation as val


def one_trajectory(x, who: str) -> list[np.ndarray]:
    """``[array (n_times, n_states)]`` from one trajectory given as an array or a nested
    list of numbers; a list of several 2-D arrays is an error that says what to do."""
    if isinstance(x, list | tuple):
        if x and all(np.ndim(e) == 2 for e in x):
            raise ValueError(f"{who} one trajectory, a 2-D array of shape (n_times, "
                             f"n_states); got a list of {len(x)} arrays. Fit one per "
                             "trajectory.")
        try:
            x = np.asarray(x, dtype=float)
        except (TypeError, ValueError):
            raise ValueError(f"{who} one trajectory, a 2-D array of shape (n_times, "
                             "n_states); got a list that is not a table of numbers.") from None
    return val.as_trajectories(x, "x")
