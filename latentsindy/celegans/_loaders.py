"""Readers for the two public layouts of the Kato et al. (2015) whole-brain recordings.

* Per-worm MATLAB v5 files (``wbdata/TS2014..._basal_1080s.mat``): a struct ``wbData``
  with ``deltaFOverF`` (frames x neurons), ``deltaFOverF_bc`` (bleach-corrected),
  ``NeuronIds`` (one cell per neuron: its candidate names, empty if unidentified),
  ``tv`` (frame times) and ``fps``. Behaviour labels live in ``sevenStateColoring.mat``
  (``sevenStateColoring.dataset.stateTimeSeries``, one code series per worm, in the
  order of the worm files sorted by name, and ``sevenStateColoring.key``).
* ``WT_NoStim.mat`` (MATLAB v7.3, i.e. HDF5): a struct ``WT_NoStim`` whose fields are
  cells with one entry per worm: ``deltaFOverF``, ``deltaFOverF_bc``,
  ``deltaFOverF_deriv``, ``NeuronNames``, ``tv``, ``fps``, ``States`` (one 0/1 series per
  behaviour) and ``dataset`` (names).

Nothing is downloaded: pass the path of the files you have. Every problem with a file is
a ``ValueError`` naming the file and what was missing.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from scipy.io import loadmat, whosmat

from ._recording import WormRecording

LABELS_FILE = "sevenStateColoring.mat"
_TRACES = ("deltaFOverF_bc", "deltaFOverF")


def load_kato(path, *, trace: str | None = None) -> list[WormRecording]:
    """Every worm in a file or folder of either layout.

    ``path`` may be ``WT_NoStim.mat`` (v7.3), one per-worm v5 file, or a folder of
    per-worm v5 files (with ``sevenStateColoring.mat`` beside them for the labels).
    ``trace`` picks the field (default: bleach-corrected ``deltaFOverF_bc`` when present).
    """
    path = Path(path).expanduser()
    if not path.exists():
        raise ValueError(f"{path}: no such file or folder. Pass WT_NoStim.mat (MATLAB "
                         "v7.3), a wbdata/ folder of per-worm .mat files, or one worm's "
                         ".mat file.")
    if path.is_dir():
        files = worm_files(path)
        if not files:
            raise ValueError(f"{path}: no per-worm .mat files in this folder.")
        return [_with_optional_labels(f, i, trace) for i, f in enumerate(files)]
    _check_file(path)
    if _is_hdf5(path):
        return load_wt_nostim(path, trace=trace)
    return [_with_optional_labels(path, None, trace)]


def _with_optional_labels(path, index, trace):
    """A worm with the labels file beside it when there is one and it fits; a labels
    file that does not fit (other worms, other frame counts) gives a warning and no
    labels, since the labels are optional here."""
    labels = path.parent / LABELS_FILE
    if not labels.exists():
        return load_kato_worm(path, trace=trace)
    try:
        return load_kato_worm(path, labels=labels, labels_index=index, trace=trace)
    except ValueError as err:
        if LABELS_FILE not in str(err):
            raise
        warnings.warn(f"{err} Loading {path.name} without behaviour labels.", stacklevel=3)
        return load_kato_worm(path, trace=trace)


def worm_files(folder) -> list[Path]:
    """Per-worm files of a folder (MATLAB v5 files holding ``wbData``), sorted by name
    (the labels file's order); other ``.mat`` files are skipped."""
    out = []
    for p in sorted(Path(folder).glob("*.mat")):
        if p.name == LABELS_FILE or _is_hdf5(p):
            continue
        try:
            if any(name == "wbData" for name, _, _ in whosmat(p)):
                out.append(p)
        except Exception:  # noqa: BLE001 - not a MAT file: not a worm file either
            continue
    return out


def load_kato_worm(path, *, labels=None, labels_index: int | None = None,
                   trace: str | None = None) -> WormRecording:
    """One worm from a per-worm MATLAB v5 file (struct ``wbData``).

    ``labels`` is the path of ``sevenStateColoring.mat``; ``labels_index`` the worm's
    position in it (default: the file's position among the ``.mat`` files of its folder
    sorted by name, as published).
    """
    path = Path(path).expanduser()
    _check_file(path)
    try:
        content = loadmat(path, simplify_cells=True)
    except Exception as err:  # scipy raises several types for a non-MAT file
        raise ValueError(f"{path}: not a readable MATLAB v5 file ({err}).") from None
    wb = content.get("wbData")
    if not isinstance(wb, dict):
        raise ValueError(f"{path}: no struct 'wbData'; variables are "
                         f"{sorted(k for k in content if not k.startswith('__'))}.")
    traces = _numeric(wb, _trace_field(wb, trace, path), path, ndim=2)
    t = _numeric(wb, "tv", path).ravel()
    fps = float(_numeric(wb, "fps", path).ravel()[0])
    ids = wb.get("NeuronIds")
    names = tuple(_first_name(e) for e in _cells(ids)) if ids is not None else ()
    if len(names) != traces.shape[1]:
        names = ("",) * traces.shape[1]
    states = state_names = None
    if labels is not None:
        if labels_index is None:
            siblings = [p.name for p in worm_files(path.parent)]
            labels_index = siblings.index(path.name) if path.name in siblings else -1
        states, state_names = _seven_states(Path(labels), labels_index, t.size)
    return WormRecording(path.stem, t, traces, names, fps, states, state_names)


def load_wt_nostim(path, *, trace: str | None = None) -> list[WormRecording]:
    """Every worm of ``WT_NoStim.mat`` (MATLAB v7.3 / HDF5; needs ``h5py``)."""
    h5py = _h5py()
    path = Path(path).expanduser()
    _check_file(path)
    if not _is_hdf5(path):
        raise ValueError(f"{path}: not a MATLAB v7.3 (HDF5) file; for per-worm v5 files "
                         f"use load_kato_worm.")
    with h5py.File(path, "r") as f:
        roots = [k for k in f if not k.startswith("#") and isinstance(f[k], h5py.Group)]
        structs = [k for k in roots if _matlab_class(f[k]) == "struct"]
        roots = structs or roots
        if not roots:
            raise ValueError(f"{path}: no struct at the top level.")
        try:
            return _read_worms(f, roots[0], path, trace)
        except (KeyError, TypeError, AttributeError, IndexError, ValueError) as err:
            if isinstance(err, ValueError) and str(path) in str(err):
                raise
            raise ValueError(f"{path}: struct '{roots[0]}' is not laid out like "
                             f"WT_NoStim.mat (one cell entry per worm): {err}") from None


def _read_worms(f, root_name, path, trace):
    root = f[root_name]
    fields = set(root.keys())
    field = _trace_field(fields, trace, path)
    for need in ("tv", "fps"):
        if need not in fields:
            raise ValueError(f"{path}: struct '{root_name}' has no field '{need}'; "
                             f"fields are {sorted(fields)}.")
    out = []
    for w in range(root[field].size):
        traces = np.asarray(_deref(f, root[field], w), dtype=float).T
        t = np.asarray(_deref(f, root["tv"], w), dtype=float).ravel()
        fps = float(np.asarray(_deref(f, root["fps"], w)).ravel()[0])
        names = (tuple(_h5_name(f, r) for r in np.ravel(_deref(f, root["NeuronNames"], w)))
                 if "NeuronNames" in fields else ())
        if len(names) != traces.shape[1]:
            names = ("",) * traces.shape[1]
        name = (_h5_text(f[np.ravel(root["dataset"][()])[w]]) if "dataset" in fields
                else "")
        states = state_names = None
        if "States" in fields:
            states, state_names = _h5_states(f[np.ravel(root["States"][()])[w]], t.size)
        out.append(WormRecording(name or f"{root_name}_{w}", t, traces, names, fps,
                                 states, state_names))
    return out


# ----------------------------------------------------------------------------- helpers
def _check_file(path):
    if not path.is_file():
        raise ValueError(f"{path}: no such file.")


def _is_hdf5(path) -> bool:
    with open(path, "rb") as fh:
        head = fh.read(1024)
    return b"\x89HDF\r\n\x1a\n" in head  # at 0 or after MATLAB's 512-byte user block


def _h5py():
    try:
        import h5py
    except ImportError:
        raise ImportError("Reading MATLAB v7.3 files needs h5py: "
                          "pip install 'latentsindy[hdf5]'.") from None
    return h5py


def _trace_field(fields, trace, path):
    if trace is not None:
        if trace not in fields:
            raise ValueError(f"{path}: no field {trace!r}; fields are {sorted(fields)}.")
        return trace
    for name in _TRACES:
        if name in fields:
            return name
    raise ValueError(f"{path}: none of the trace fields {list(_TRACES)}; fields are "
                     f"{sorted(fields)}.")


def _numeric(struct, field, path, ndim=None):
    if field not in struct:
        raise ValueError(f"{path}: 'wbData' has no field {field!r}; fields are "
                         f"{sorted(struct)}.")
    try:
        arr = np.asarray(struct[field], dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: field {field!r} is not numeric.") from None
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{path}: field {field!r} must be {ndim}-D; got shape {arr.shape}.")
    return arr


def _cells(value):
    if isinstance(value, np.ndarray) and value.dtype == object:
        return list(value.ravel())
    if isinstance(value, list | tuple):
        return list(value)
    return [value]


def _first_name(entry) -> str:
    """First non-empty string in a (possibly nested) cell entry."""
    if isinstance(entry, str):
        return entry.strip()
    if isinstance(entry, np.ndarray) and entry.dtype.kind in "US":
        return str(entry.ravel()[0]).strip() if entry.size else ""
    if isinstance(entry, np.ndarray | list | tuple):
        for item in _cells(entry if not isinstance(entry, np.ndarray) else entry.astype(object)):
            name = _first_name(item)
            if name:
                return name
    return ""


def _seven_states(path, index, n_frames):
    _check_file(path)
    try:
        content = loadmat(path, simplify_cells=True)
    except Exception as err:
        raise ValueError(f"{path}: not a readable MATLAB v5 file ({err}).") from None
    coloring = content.get("sevenStateColoring")
    if not isinstance(coloring, dict) or "dataset" not in coloring:
        raise ValueError(f"{path}: no struct 'sevenStateColoring' with a 'dataset' field.")
    dataset = coloring["dataset"]
    series = ([d["stateTimeSeries"] for d in dataset] if isinstance(dataset, list)
              else _cells(dataset["stateTimeSeries"]))
    if not 0 <= index < len(series):
        raise ValueError(f"{path}: labels for {len(series)} worms; asked for worm {index}. "
                         "Pass labels_index (the worm's position among the per-worm files "
                         "sorted by name).")
    codes = np.asarray(series[index], dtype=float).ravel()
    if codes.size != n_frames:
        raise ValueError(f"{path}: worm {index} has {codes.size} labels for {n_frames} "
                         f"frames; check labels_index.")
    key = coloring.get("key")
    names = tuple(_first_name(k) for k in _cells(key)) if key is not None else None
    return np.where(np.isfinite(codes), codes - 1, -1).astype(int), names


def _deref(f, refs, i):
    """Entry i of a cell field (a dataset of object references)."""
    data = refs[()]
    if not (isinstance(data, np.ndarray) and data.dtype == object):
        raise TypeError(f"field '{refs.name}' is not a cell of references")
    return f[np.ravel(data)[i]][()]


def _matlab_class(obj) -> str:
    value = obj.attrs.get("MATLAB_class", b"")
    return value.decode() if isinstance(value, bytes) else str(value)


def _h5_text(obj) -> str:
    data = np.asarray(obj[()])
    if data.dtype.kind in "ui" and obj.attrs.get("MATLAB_class", b"") in (b"char", "char"):
        return "".join(chr(int(c)) for c in data.ravel(order="F") if c)
    return ""


def _h5_name(f, ref) -> str:
    """A neuron's name: a char array, an empty cell, or a cell of candidate names."""
    obj = f[ref]
    data = obj[()]
    if isinstance(data, np.ndarray) and data.dtype == object:
        for r in data.ravel():
            name = _h5_name(f, r)
            if name:
                return name
        return ""
    return _h5_text(obj).strip()


def _h5_states(group, n_frames):
    names = tuple(sorted(group.keys()))
    if not names:
        return None, None
    onehot = np.column_stack([np.asarray(group[k][()], dtype=float).ravel() for k in names])
    if onehot.shape[0] != n_frames:
        return None, None
    labels = np.where(onehot.max(axis=1) > 0, onehot.argmax(axis=1), -1)
    return labels.astype(int), names
