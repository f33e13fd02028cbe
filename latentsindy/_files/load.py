"""``latentsindy.load``: read any latentsindy file, whichever format it holds."""

from __future__ import annotations

import zipfile
from pathlib import Path

from . import model_file, result_file
from .container import Refused, read


def load(path):
    """Read a file written by ``HiddenDiscovery.save`` or ``DynamicSINDy.save``.

    Returns the HiddenDiscovery or the fitted DynamicSINDy. Equations are rebuilt from
    their stored structure (a whitelist of node types and the result's own state
    names), networks from their settings with the stored weights; nothing in the file
    is unpickled or evaluated. A file that is neither, or is damaged, is refused with a
    ValueError that names it; a path to no file raises FileNotFoundError.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file (expected the .npz written by "
                                "HiddenDiscovery.save or DynamicSINDy.save).")
    try:
        meta, arrays = read(path)
        if meta.get("format") == model_file.FORMAT:
            if meta.get("version") not in model_file.READABLE:
                raise Refused(f"DynamicSINDy file version {meta.get('version')!r}; this "
                              f"latentsindy reads versions "
                              f"{', '.join(map(str, model_file.READABLE))}")
            return model_file.read_model(meta, arrays)
        if (meta.get("format") != result_file.FORMAT
                or meta.get("version") not in result_file.READABLE):
            raise Refused(f"not a saved HiddenDiscovery or DynamicSINDy (format "
                          f"{meta.get('format')!r}, version {meta.get('version')!r}; "
                          f"expected {result_file.FORMAT!r}, versions "
                          f"{', '.join(map(str, result_file.READABLE))}, or "
                          f"{model_file.FORMAT!r})")
        return result_file.read_result(meta, arrays)
    except Refused as err:
        raise ValueError(f"{path} cannot be loaded: {err}.") from None
    except (KeyError, TypeError, AttributeError, ValueError, OSError, RuntimeError,
            zipfile.BadZipFile) as err:
        if str(err).startswith(f"{path} cannot be loaded"):
            raise  # read's message already names the file and the problem
        detail = " ".join(str(err).split())  # one line
        raise ValueError(f"{path} cannot be loaded: missing or malformed entry "
                         f"({type(err).__name__}: {detail}).") from None
