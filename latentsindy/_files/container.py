"""The container every latentsindy file shares: a ``.npz`` of plain arrays plus one
JSON document (``meta``) that names the format and its version. Nothing is pickled."""

from __future__ import annotations

import contextlib
import json
import os
import zipfile
from pathlib import Path

import numpy as np


class Refused(ValueError):
    """A file entry that is malformed or outside what a format allows."""


def write(path, meta_json: str, arrays: dict) -> None:
    """Write the JSON document and the arrays to ``path`` (compressed ``.npz``), whole or
    not at all: to a file beside it, then moved over it, so a write that fails (a full
    disk) leaves an earlier file of that name as it was."""
    path = Path(path)
    part = path.with_name(f".{path.name}.{os.getpid()}.part")
    try:
        with open(part, "wb") as fh:
            np.savez_compressed(fh, meta=np.array(meta_json), **arrays)
        os.replace(part, path)
    finally:
        with contextlib.suppress(FileNotFoundError):
            part.unlink()


def read(path):
    """(meta, arrays) of a latentsindy ``.npz``; ValueError naming the file otherwise."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["meta"])) if "meta" in data.files else {}
            arrays = {k: data[k] for k in data.files if k != "meta"}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):
        raise ValueError(f"{path} cannot be loaded: not a latentsindy file (expected the "
                         ".npz written by HiddenDiscovery.save or DynamicSINDy.save).") from None
    return meta, arrays
