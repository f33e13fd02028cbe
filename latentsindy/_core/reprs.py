"""One-line reprs: an estimator as scikit-learn prints one (its class and the
parameters that differ from their defaults)."""

from __future__ import annotations

import inspect

import numpy as np


def _differs(value, default) -> bool:
    if value is default:
        return False
    if isinstance(value, np.ndarray) or isinstance(default, np.ndarray):
        return True
    try:
        return bool(value != default)
    except (TypeError, ValueError):  # values whose comparison is not a bool
        return True


def estimator_repr(obj, params: dict, width: int = 100) -> str:
    """``Class(name=value, ...)`` with the parameters of ``params`` that differ from the
    defaults of ``type(obj).__init__``; arrays are shown by their shape.

    Examples
    --------
    >>> class Model:
    ...     def __init__(self, a=1, *, b="x"):
    ...         self.a, self.b = a, b
    >>> m = Model(b="y")
    >>> estimator_repr(m, {"a": m.a, "b": m.b})
    "Model(b='y')"
    """
    defaults = {k: p.default for k, p in inspect.signature(type(obj).__init__).parameters.items()
                if p.default is not inspect.Parameter.empty}
    shown = []
    for name, value in params.items():
        if name in defaults and not _differs(value, defaults[name]):
            continue
        text = (f"<array of shape {value.shape}>" if isinstance(value, np.ndarray)
                else repr(value))
        shown.append(f"{name}={text}")
    one = f"{type(obj).__name__}({', '.join(shown)})"
    if len(one) <= width:
        return one
    indent = " " * (len(type(obj).__name__) + 1)
    return f"{type(obj).__name__}(" + f",\n{indent}".join(shown) + ")"
