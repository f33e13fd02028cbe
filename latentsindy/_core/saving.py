"""The one hook between result types and their file formats.

A result's ``save(path)`` method calls :func:`save`; each file format
(:mod:`latentsindy._files`) registers the writer of its type with ``save.register``.
So formats depend on the result types and never the reverse, and a result type knows
nothing of how it is stored.
"""

from __future__ import annotations

from functools import singledispatch


@singledispatch
def save(obj, path) -> None:
    """Write ``obj`` to ``path`` with the file format registered for its type."""
    raise TypeError(f"latentsindy has no file format for {type(obj).__name__} objects; "
                    "results of discover_hidden and fitted DynamicSINDy models can be saved.")
