"""Checks on user input, done once at the boundary, with messages that say the fix."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

MIN_TIMES = 16  # shorter series cannot support a derivative estimate plus a time-varying fit


_KINDS = {"b": "boolean", "c": "complex", "O": "object", "U": "string", "S": "bytes",
          "M": "datetime", "m": "timedelta", "V": "structured"}


def numeric_2d(x, what: str) -> np.ndarray:
    """A real float array of shape (n_times, n_states); NaN allowed (checked by callers)."""
    raw = x if isinstance(x, np.ndarray) else None
    if raw is None:
        try:
            raw = np.asarray(x)
        except (TypeError, ValueError) as err:
            raise TypeError(f"{what} must be a numeric array of shape (n_times, n_states); got "
                            f"{type(x).__name__} that cannot be converted ({err}).") from None
    if raw.dtype.kind in _KINDS:
        hint = ("take the real part or the modulus yourself (np.real, np.abs)"
                if raw.dtype.kind == "c" else "convert it to floats (e.g. x.astype(float))")
        raise TypeError(f"{what} must hold real numbers (float or int); got a "
                        f"{_KINDS[raw.dtype.kind]} array (dtype {raw.dtype}) of shape "
                        f"{raw.shape}: {hint}.")
    arr = np.asarray(raw, dtype=float)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(
            f"{what} must have shape (n_times, n_states); got shape {arr.shape}. "
            "Pass several trajectories as a list of 2-D arrays, not a stacked 3-D array."
        )
    if arr.shape[0] < 2 or arr.shape[1] == 0:
        raise ValueError(f"{what} must hold a time series of shape (n_times, n_states); got "
                         f"shape {arr.shape}: at least {MIN_TIMES} samples of at least one "
                         f"state are needed (hundreds are better).{_transposed(arr, what)}")
    return arr


def _transposed(arr, what: str) -> str:
    """A hint for an array that looks transposed (few rows, many columns), else ''."""
    if arr.ndim == 2 and arr.shape[0] < MIN_TIMES <= arr.shape[1]:
        return (f" It looks transposed: rows are samples and columns states; pass "
                f"{what}.T.")
    return ""


def _as_2d(x, what: str) -> np.ndarray:
    arr = numeric_2d(x, what)
    if not np.all(np.isfinite(arr)):
        bad = int(np.sum(~np.isfinite(arr)))
        raise ValueError(
            f"{what} contains {bad} NaN or infinite value(s) (first at row "
            f"{int(np.argwhere(~np.isfinite(arr))[0, 0])}); remove or interpolate them first "
            "(discover_hidden splits a recording at its gaps itself)."
        )
    return arr


def _ragged(rows) -> bool:
    return len({np.shape(r) for r in rows}) > 1


def as_trajectories(x, what: str = "x") -> list[np.ndarray]:
    """Return a list of finite 2-D float arrays with a common number of states."""
    if isinstance(x, list | tuple) and len(x) > 0 and np.ndim(x[0]) <= 1:
        x = np.asarray(x, dtype=object if _ragged(x) else None)  # rows or numbers: one series
    if isinstance(x, list | tuple):
        if len(x) == 0:
            raise ValueError(f"{what} is an empty list; pass at least one trajectory.")
        trajs = [_as_2d(xi, f"{what}[{k}]") for k, xi in enumerate(x)]
    else:
        trajs = [_as_2d(x, what)]
    n_states = {tr.shape[1] for tr in trajs}
    if len(n_states) > 1:
        raise ValueError(
            f"All trajectories in {what} must have the same number of states; "
            f"got {sorted(n_states)}."
        )
    listed = isinstance(x, list | tuple)
    for k, tr in enumerate(trajs):
        if tr.shape[0] < MIN_TIMES:
            name = f"{what}[{k}]" if listed else what
            raise ValueError(
                f"Series too short: trajectory {k} of {what} has {tr.shape[0]} time points; "
                f"at least {MIN_TIMES} are needed (hundreds are better).{_transposed(tr, name)}"
            )
    return trajs


def as_times(t, trajectories: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Turn a spacing, an array of times, or a list of either into one time array per trajectory."""
    n = len(trajectories)
    if isinstance(t, list | tuple) and n > 1:
        if len(t) != n:
            raise ValueError(f"t is a list of {len(t)} entries but x has {n} trajectories.")
        return [_one_times(ti, tr.shape[0], f"t[{k}]") for k, (ti, tr) in
                enumerate(zip(t, trajectories, strict=True))]
    if isinstance(t, list | tuple) and len(t) == 1 and np.ndim(t[0]) >= 1:
        t = t[0]
    return [_one_times(t, tr.shape[0], "t") for tr in trajectories]


def _one_times(t, n_times: int, what: str, missing=None) -> np.ndarray:
    if t is None:
        raise TypeError(f"{what} is required: a sample spacing (float) or an array of times.")
    if np.ndim(t) == 0:
        kind = np.asarray(t).dtype.kind
        if kind not in "iuf":
            raise TypeError(f"The sample spacing {what} must be a positive real number; got "
                            f"{t!r} ({type(t).__name__}). Pass a float, or an array of "
                            "sample times.")
        dt = float(t)
        if not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"The sample spacing {what} must be a positive number; got {dt!r}.")
        return np.arange(n_times) * dt
    raw = np.asarray(t)
    if raw.dtype.kind in _KINDS:
        raise TypeError(f"{what} must hold real sample times (float or int); got a "
                        f"{_KINDS[raw.dtype.kind]} array (dtype {raw.dtype}); convert "
                        "datetimes to seconds (or any unit) first.")
    arr = np.array(raw, dtype=float, copy=True)
    if arr.ndim != 1:
        raise ValueError(f"{what} must be 1-D; got shape {arr.shape}.")
    if arr.shape[0] != n_times:
        raise ValueError(
            f"Length mismatch: {what} has {arr.shape[0]} times but x has {n_times} rows; "
            "they must match." + (" x is read with one row per sample, shape (n_times, "
                                  "n_states): if its rows are states, pass x.T."
                                  if n_times < arr.shape[0] else "")
        )
    keep = np.ones(n_times, dtype=bool) if missing is None else ~missing
    if not np.all(np.isfinite(arr[keep])):
        raise ValueError(f"{what} contains NaN or infinite times; give every sample a time.")
    rows = np.flatnonzero(keep)
    steps = np.diff(arr[rows])
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        a, b = rows[k], rows[k + 1]
        raise ValueError(
            f"{what} must be strictly increasing; {what}[{a}]={float(arr[a])!r} is followed "
            f"by {what}[{b}]={float(arr[b])!r}. Sort the samples (with their rows of x) or drop "
            "duplicate times."
        )
    return arr


def check_feature_names(names, n_states: int, what: str = "feature_names") -> list[str]:
    """State names: default ``x0, x1, ...``; must be unique identifiers."""
    if names is None:
        return [f"x{i}" for i in range(n_states)]
    names = [str(n) for n in names]
    if len(names) != n_states:
        raise ValueError(f"{what} has {len(names)} names but the data have {n_states} states.")
    if len(set(names)) != len(names):
        raise ValueError(f"{what} must be unique; got {names}.")
    for n in names:
        if not n.isidentifier():
            raise ValueError(
                f"{what} must be valid identifiers (letters, digits, underscores); got {n!r}."
            )
    return names


def check_positive(value, what: str, *, allow_zero: bool = False, integer: bool = False):
    """``value`` as a float (an int with ``integer``) that is finite and > 0 (>= 0 with
    ``allow_zero``); text and booleans are refused, not converted."""
    kind = int if integer else float
    if isinstance(value, (str, bytes, bool, np.bool_)) or (
            isinstance(value, np.ndarray) and value.dtype.kind not in "iuf"):
        raise TypeError(f"{what} must be a number; got {value!r} "
                        f"({type(value).__name__}): pass the number itself (15, not '15').")
    try:
        v = kind(value)
    except (TypeError, ValueError, OverflowError):
        if not integer or not isinstance(value, (float, np.floating)):
            raise TypeError(f"{what} must be a number; got {value!r}.") from None
        v = float(value)  # an infinite or NaN float where an integer is due: said below
    if integer and v != value and np.isfinite(v):
        raise TypeError(f"{what} must be an integer; got {value!r}.")
    bound = ">= 0" if allow_zero else "> 0"
    if not np.isfinite(v):
        raise ValueError(f"{what} must be a finite number {bound}; got {value!r}.")
    if v < 0 if allow_zero else v <= 0:
        raise ValueError(f"{what} must be {bound}; got {value!r}.")
    return v


def check_seconds(value, what: str):
    """A time budget: seconds > 0 as a float, or None for no limit (``None`` or
    infinity)."""
    if value is None or (isinstance(value, (float, np.floating)) and value == np.inf):
        return None
    try:
        return check_positive(value, what)
    except ValueError:
        raise ValueError(f"{what} must be a number of seconds > 0 (leave it out for no "
                         f"limit); got {value!r}.") from None


def term_mask(spec, states, features, what, *, default, unnamed):
    """Bool (n_states, n_features) mask from None (``default``), a dict naming the terms
    of some states (states not named get ``unnamed``) or a bool array."""
    shape = (len(states), len(features))
    if spec is None:
        return np.full(shape, default)
    if isinstance(spec, dict):
        mask = np.full(shape, unnamed)
        for state, feats in spec.items():
            if state not in states:
                raise ValueError(f"{what} names state {state!r}; states are {list(states)}.")
            if isinstance(feats, str):
                feats = [feats]
            mask[states.index(state)] = False
            for f in feats:
                if f not in features:
                    raise ValueError(f"{what}[{state!r}] names feature {f!r}; library features "
                                     f"are {list(features)}.")
                mask[states.index(state), features.index(f)] = True
        return mask
    arr = np.asarray(spec)
    if arr.shape != shape or arr.dtype != bool:
        raise ValueError(f"{what} must be a dict {{state: [features]}} or a bool array of "
                         f"shape {shape}; got {type(spec).__name__} with shape "
                         f"{getattr(arr, 'shape', None)} and dtype {arr.dtype}.")
    return arr.copy()


def free_rows(spec, states):
    """Equations whose support is learned (not fixed by the user)."""
    if spec is None:
        return np.ones(len(states), dtype=bool)
    if isinstance(spec, dict):
        return np.array([s not in spec for s in states])
    return np.zeros(len(states), dtype=bool)


def check_device(device) -> str:
    """A torch device name that exists on this machine ("cpu", "cuda", "cuda:1", ...)."""
    import torch

    expected = (f"device must be 'cpu' or a CUDA device ('cuda', 'cuda:0', ...); got "
                f"{device!r}.")
    try:
        dev = torch.device(device)
    except (TypeError, RuntimeError):
        raise ValueError(expected) from None
    if dev.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if dev.index is not None and dev.index >= count or count == 0:
            raise ValueError(f"device {device!r} is not available: this machine has {count} "
                             "CUDA device(s) and this torch build "
                             f"({torch.__version__}) {'has' if torch.version.cuda else 'lacks'} "
                             "CUDA support; use device='cpu' or a CUDA build of torch.")
    elif dev.type != "cpu":
        raise ValueError(expected)
    return str(dev)
