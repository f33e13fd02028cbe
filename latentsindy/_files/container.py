"""The container every latentsindy file shares: a ``.npz`` of plain arrays plus one
JSON document (``meta``) that names the format and its version. Nothing is pickled."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np


class Refused(ValueError):
    """A file entry that is malformed or outside what a format allows."""


def write(path, meta_json: str, arrays: dict) -> None:
    """Write the JSON document and the arrays to ``path`` (compressed ``.npz``)."""
    with open(Path(path), "wb") as fh:
        np.savez_compressed(fh, meta=np.array(meta_json), **arrays)


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
