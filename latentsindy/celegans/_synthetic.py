"""Synthetic worms with known truth, written in both public file layouts.

The seed paper's model (supplement 3.1): ``xdot = y``,
``ydot = -0.002 x^3 + 0.0087 x^2 + 0.05 x - 0.22 y + u``, with u switching between
-0.266 and 0.044 at random times, mixed into noisy "neurons" along a random unit axis
(so the first principal component's score is x plus projected noise) and sampled at
the worm's frame rate.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp
from scipy.io import savemat

from ._loaders import LABELS_FILE, _h5py
from ._recording import WormRecording

PAPER_CUBIC = {"x^3": -0.002, "x^2": 0.0087, "x": 0.05, "y": -0.22}
PAPER_LEVELS = (-0.266, 0.044)
KATO_FPS = 1.0 / 0.35749752
_MATLAB_HEADER = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: synthetic HDF5 schema 1.00 ."


@dataclass(frozen=True)
class SwitchingTruth:
    """What generated a synthetic worm: x(t), the input u(t), its switch times, the
    cubic's coefficients and the two levels."""

    t: np.ndarray = field(repr=False)
    x: np.ndarray = field(repr=False)
    u: np.ndarray = field(repr=False)
    switch_times: np.ndarray
    cubic: dict
    levels: tuple


def switching_worm(*, n_frames: int = 3000, n_neurons: int = 100, fps: float = KATO_FPS,
                   neuron_noise: float = 0.5, dwell=(40.0, 140.0), x0: float = -5.25,
                   cubic=None, levels=PAPER_LEVELS, name: str = "synthetic_worm",
                   seed: int = 0) -> tuple[WormRecording, SwitchingTruth]:
    """A worm whose first principal component follows the paper's switching cubic.

    Parameters
    ----------
    n_frames, n_neurons, fps
        Recording size and frame rate (default: the Kato data's 2.8 Hz).
    neuron_noise : float
        Each neuron's noise standard deviation as a multiple of the mean neuron's
        signal standard deviation.
    dwell : (float, float)
        Times between switches are uniform on this range (seconds).
    x0 : float
        Initial x (default: the reversal fixed point); y starts at 0.
    cubic : dict, optional
        Coefficients of ``x^3, x^2, x, y`` in ydot (default: the paper's).
    levels : (float, float)
        The two values of u; the series starts at the first.
    seed : int
    """
    cubic = dict(PAPER_CUBIC if cubic is None else cubic)
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / fps
    switches = [rng.uniform(*dwell)]
    while switches[-1] < t[-1]:
        switches.append(switches[-1] + rng.uniform(*dwell))
    switches = np.array(switches[:-1])

    def u_at(time):
        return np.asarray(levels)[np.searchsorted(switches, time, side="right") % 2]

    def rhs(time, s):
        x, y = s
        return [y, (cubic["x^3"] * x**3 + cubic["x^2"] * x**2 + cubic["x"] * x
                    + cubic["y"] * y + u_at(time))]

    edges = np.concatenate([[0.0], switches, [t[-1]]])
    x = np.empty(n_frames)
    state = [x0, 0.0]
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):  # integrate piece by piece
        inside = (t >= lo) & (t < hi)
        sol = solve_ivp(rhs, (lo, hi), state, t_eval=np.concatenate([t[inside], [hi]]),
                        rtol=1e-9, atol=1e-11, max_step=0.1)
        x[inside] = sol.y[0, :-1]
        state = sol.y[:, -1]
    x[-1] = state[0]
    axis = rng.normal(size=n_neurons)
    axis[: int(0.7 * n_neurons)] = np.abs(axis[: int(0.7 * n_neurons)])
    axis /= np.linalg.norm(axis)
    noise = neuron_noise * np.mean(np.abs(axis)) * x.std()
    traces = np.outer(x, axis) + rng.normal(scale=noise, size=(n_frames, n_neurons))
    names = tuple(f"N{i:03d}" if i % 3 == 0 else "" for i in range(n_neurons))
    states = (np.searchsorted(switches, t, side="right") % 2).astype(int)
    recording = WormRecording(name, t, traces, names, fps, states, ("low u", "high u"))
    truth = SwitchingTruth(t, x, u_at(t), switches, cubic, tuple(levels))
    return recording, truth


def write_kato_folder(folder, recordings) -> list[Path]:
    """Write recordings as per-worm MATLAB v5 files plus ``sevenStateColoring.mat``
    (the layout of ``wbdata/``). Returns the worm files, sorted by name."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for rec in recordings:
        ids = np.empty((1, len(rec.neuron_names)), dtype=object)
        for i, n in enumerate(rec.neuron_names):
            cell = np.empty((1, 1 if n else 0), dtype=object)
            if n:
                cell[0, 0] = n
            ids[0, i] = cell
        wb = {"deltaFOverF": rec.traces, "deltaFOverF_bc": rec.traces,
              "deltaFOverF_deriv": np.gradient(rec.traces, rec.t, axis=0),
              "NeuronIds": ids, "tv": rec.t[:, None], "fps": rec.fps}
        path = folder / f"{rec.name}.mat"
        savemat(path, {"wbData": wb}, do_compression=True)
        paths.append(path)
    ordered = sorted(recordings, key=lambda r: r.name)
    series = np.empty((1, len(ordered)), dtype=object)
    for i, rec in enumerate(ordered):
        codes = np.zeros(rec.t.size) if rec.states is None else rec.states + 1.0
        series[0, i] = codes[:, None]
    names = ordered[0].state_names or ("unlabelled",)
    key = np.empty((1, len(names)), dtype=object)
    key[0, :] = list(names)
    savemat(folder / LABELS_FILE, {"sevenStateColoring": {
        "key": key, "dataset": {"stateTimeSeries": series}}}, do_compression=True)
    return sorted(paths)


def write_wt_nostim(path, recordings, *, struct: str = "WT_NoStim") -> Path:
    """Write recordings in the layout of ``WT_NoStim.mat`` (MATLAB v7.3 / HDF5)."""
    h5py = _h5py()
    path = Path(path)
    refs_made = [0]

    def put(group, data, matlab_class, **attrs):
        refs_made[0] += 1
        ds = group.create_dataset(f"r{refs_made[0]}", data=data)
        ds.attrs["MATLAB_class"] = np.bytes_(matlab_class)
        for k, v in attrs.items():
            ds.attrs[k] = v
        return ds.ref

    def text(group, s):
        if not s:
            return put(group, np.zeros(2, dtype=np.uint64), "char", MATLAB_empty=np.uint8(1))
        return put(group, np.array([[ord(c)] for c in s], dtype=np.uint16), "char")

    with h5py.File(path, "w", userblock_size=512) as f:
        refs = f.create_group("#refs#")
        root = f.create_group(struct)
        root.attrs["MATLAB_class"] = np.bytes_("struct")
        ref_dtype = h5py.special_dtype(ref=h5py.Reference)
        fields = {k: [] for k in ("deltaFOverF", "deltaFOverF_bc", "deltaFOverF_deriv",
                                  "NeuronNames", "tv", "fps", "States", "dataset")}
        for rec in recordings:
            fields["deltaFOverF"].append(put(refs, rec.traces.T, "double"))
            fields["deltaFOverF_bc"].append(put(refs, rec.traces.T, "double"))
            fields["deltaFOverF_deriv"].append(
                put(refs, np.gradient(rec.traces, rec.t, axis=0).T, "double"))
            names = np.array([[text(refs, n)] for n in rec.neuron_names], dtype=ref_dtype)
            fields["NeuronNames"].append(put(refs, names, "cell"))
            fields["tv"].append(put(refs, rec.t[None, :], "double"))
            fields["fps"].append(put(refs, np.array([[rec.fps]]), "double"))
            fields["dataset"].append(text(refs, rec.name))
            states = refs.create_group(f"s{len(fields['States'])}")
            states.attrs["MATLAB_class"] = np.bytes_("struct")
            for k, label in enumerate(rec.state_names or ()):
                onehot = (rec.states == k).astype(float)[None, :]
                states.create_dataset(label.replace(" ", "_"), data=onehot)
            fields["States"].append(states.ref)
        for k, v in fields.items():
            ds = root.create_dataset(k, data=np.array(v, dtype=ref_dtype)[:, None])
            ds.attrs["MATLAB_class"] = np.bytes_("cell")
    with open(path, "r+b") as fh:  # MATLAB's text header in the user block
        fh.write(_MATLAB_HEADER.ljust(116) + b"\x00" * 8 + b"\x00\x02IM")
    return path
