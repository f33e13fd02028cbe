"""Reading named numeric columns from CSV, NPZ and HDF5 files (for the command line).

Every problem is a :class:`DataError` whose message names the file and says what was
expected, what was found and what to do.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np


class DataError(ValueError):
    """A data file that cannot be read as the columns asked for."""


def read_columns(path, names, missing=()) -> dict[str, np.ndarray]:
    """Columns ``names`` of the file at ``path`` as float arrays of one length.

    Columns named in ``missing`` may have missing values (an empty CSV field, ``nan``),
    returned as NaN; anywhere else a missing value is an error.
    CSV: a header row of column names, then numbers. NPZ and HDF5 (``.h5``, ``.hdf5``):
    each column is a 1-D array (an HDF5 dataset path such as ``run1/x`` for groups); a
    2-D array ``a`` offers its columns as ``a:0``, ``a:1``, ...
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"{path}: no such file.")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        columns = _csv(path)
    elif suffix == ".npz":
        columns = _npz(path)
    elif suffix in (".h5", ".hdf5"):
        columns = _hdf5(path)
    else:
        raise DataError(f"{path}: unknown format {suffix!r}; expected .csv, .npz, .h5 or "
                        ".hdf5.")
    out = {}
    for name in names:
        if name not in columns:
            raise DataError(f"{path}: no column {name!r}; columns are {sorted(columns)}.")
        out[name] = _numeric(columns[name], name, path, name in missing)
    lengths = {len(v) for v in out.values()}
    if len(lengths) > 1:
        raise DataError(f"{path}: columns {list(names)} have different lengths "
                        f"{[len(v) for v in out.values()]}.")
    return out


def _numeric(values, name, path, missing_ok=False):
    if isinstance(values, list):  # CSV text
        parsed = np.empty(len(values))
        for row, text in enumerate(values):
            if text == "" and not missing_ok:
                raise DataError(f"{path}: column {name!r} has a missing or infinite value "
                                f"in data row {row + 1}; remove or fill it.")
            try:
                parsed[row] = np.nan if text == "" else float(text)
            except ValueError:
                raise DataError(f"{path}: column {name!r} is not numeric: {text!r} in data "
                                f"row {row + 1}.") from None
        values = parsed
    arr = np.asarray(values)
    if arr.dtype.kind not in "fiu" or arr.ndim != 1:
        raise DataError(f"{path}: column {name!r} must be a 1-D numeric array; got dtype "
                        f"{arr.dtype}, shape {arr.shape}.")
    arr = arr.astype(float)
    if missing_ok:
        arr[~np.isfinite(arr)] = np.nan
    elif not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise DataError(f"{path}: column {name!r} has a missing or infinite value in data "
                        f"row {bad + 1}; remove or fill it.")
    return arr


def _csv(path):
    try:
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise DataError(f"{path}: cannot be read as CSV ({err}).") from None
    rows = [r for r in rows if r]
    if len(rows) < 2:
        raise DataError(f"{path}: expected a header row of column names and data rows; "
                        f"found {len(rows)} row(s).")
    header = [h.strip() for h in rows[0]]
    columns = {h: [] for h in header}
    for k, row in enumerate(rows[1:], start=1):
        if len(row) != len(header):
            raise DataError(f"{path}: data row {k} has {len(row)} fields; the header has "
                            f"{len(header)}.")
        for h, value in zip(header, row, strict=True):
            columns[h].append(value.strip())
    return columns


def _split(name, arr, columns):
    if arr.ndim == 2:
        for j in range(arr.shape[1]):
            columns[f"{name}:{j}"] = arr[:, j]
    columns[name] = arr


def _npz(path):
    columns = {}
    try:
        with np.load(path, allow_pickle=False) as data:
            for key in data.files:
                _split(key, np.asarray(data[key]), columns)
    except (OSError, ValueError) as err:
        raise DataError(f"{path}: cannot be read as NPZ ({err}).") from None
    return columns


def _hdf5(path):
    try:
        import h5py
    except ImportError:
        raise DataError(f"{path}: reading HDF5 needs h5py; install it with "
                        'pip install "latentsindy[hdf5]" (or pip install h5py).') from None
    columns = {}
    try:
        with h5py.File(path, "r") as fh:
            def visit(name, obj):
                if isinstance(obj, h5py.Dataset) and obj.ndim in (1, 2):
                    _split(name, np.asarray(obj[()]), columns)
            fh.visititems(visit)
    except OSError as err:
        raise DataError(f"{path}: cannot be read as HDF5 ({err}).") from None
    return columns
