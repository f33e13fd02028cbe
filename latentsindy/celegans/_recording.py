"""One worm's whole-brain recording and its first principal component."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class WormRecording:
    """Calcium traces of one worm.

    Attributes
    ----------
    name : str
        Dataset name (file stem or the entry's name).
    t : ndarray (n_frames,)
        Frame times in seconds.
    traces : ndarray (n_frames, n_neurons)
        Fluorescence traces (Delta F / F).
    neuron_names : tuple of str
        Identified neuron per column, ``""`` where the neuron is not identified.
    fps : float
        Frame rate (Hz).
    states : ndarray of int (n_frames,) or None
        Behaviour label per frame (index into ``state_names``), -1 where unlabelled.
    state_names : tuple of str or None
        Behaviour names.
    """

    name: str
    t: np.ndarray = field(repr=False)
    traces: np.ndarray = field(repr=False)
    neuron_names: tuple = field(repr=False)
    fps: float
    states: np.ndarray | None = field(repr=False, default=None)
    state_names: tuple | None = None

    def __post_init__(self):
        t = np.asarray(self.t, dtype=float).ravel()
        traces = np.asarray(self.traces, dtype=float)
        if traces.ndim != 2 or traces.shape[0] != t.size:
            raise ValueError(f"{self.name}: traces must be (n_frames, n_neurons) with "
                             f"n_frames = len(t) = {t.size}; got shape {traces.shape}.")
        if t.size < 50 or np.any(np.diff(t) <= 0):
            raise ValueError(f"{self.name}: need >= 50 frames at increasing times; got "
                             f"{t.size} frames.")
        if len(self.neuron_names) != traces.shape[1]:
            raise ValueError(f"{self.name}: {len(self.neuron_names)} neuron names for "
                             f"{traces.shape[1]} traces.")
        if self.states is not None and np.asarray(self.states).shape != t.shape:
            raise ValueError(f"{self.name}: states must have one label per frame "
                             f"({t.size}); got shape {np.asarray(self.states).shape}.")
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "traces", traces)
        object.__setattr__(self, "neuron_names", tuple(str(n) for n in self.neuron_names))
        object.__setattr__(self, "fps", float(self.fps))

    def first_component(self, *, center: bool = False) -> Component:
        """The first principal component of the traces (see :class:`Component`).

        The axis is the leading eigenvector of the traces' covariance (neurons with NaN
        frames are dropped). By default the score is the projection of Delta F / F
        itself, not of its deviation from the recording mean: x = 0 then means every
        neuron at baseline fluorescence, a physical origin, whereas the mean depends on
        how long this worm spent in each behaviour. ``center=True`` projects deviations.
        The sign is fixed so that the loadings sum to a positive number.
        """
        traces = self.traces
        good = np.all(np.isfinite(traces), axis=0)
        if good.sum() < 2:
            raise ValueError(f"{self.name}: fewer than 2 neurons without NaN frames.")
        data = traces[:, good]
        mean = data.mean(axis=0)
        _, s, vt = np.linalg.svd(data - mean, full_matrices=False)
        axis = vt[0] * (1.0 if vt[0].sum() >= 0 else -1.0)
        x = (data - mean) @ axis if center else data @ axis
        loadings = np.zeros(traces.shape[1])
        loadings[good] = axis
        return Component(self.name, self.t, x, loadings, float(s[0] ** 2 / np.sum(s**2)))


@dataclass(frozen=True)
class Component:
    """First principal component of a recording.

    Attributes
    ----------
    name : str
    t : ndarray (n_frames,)
    x : ndarray (n_frames,)
        Scores.
    loadings : ndarray (n_neurons,)
        Unit-norm axis (0 for neurons dropped for NaNs).
    explained : float
        Fraction of the variance along the axis.
    """

    name: str
    t: np.ndarray = field(repr=False)
    x: np.ndarray = field(repr=False)
    loadings: np.ndarray = field(repr=False)
    explained: float
