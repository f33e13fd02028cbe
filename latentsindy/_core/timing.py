"""Where a discovery's time goes: wall time by stage, exclusive of nested stages.

``with recording() as times:`` collects; inside it, ``with stage("name"):`` adds the
block's wall time to ``times["name"]`` minus the time of stages nested in it (so the
totals add up to the recorded block). Outside ``recording`` a stage costs one context
lookup. Thread- and task-local (a ``ContextVar``).
"""

from __future__ import annotations

import contextlib
import functools
import time
from contextvars import ContextVar

_active: ContextVar[list | None] = ContextVar("latentsindy_timing", default=None)


@contextlib.contextmanager
def recording():
    """Collect stage times in a dict {stage: seconds}; time outside every stage is
    ``"other"``."""
    totals: dict[str, float] = {}
    stack = [["other", time.perf_counter(), 0.0]]  # [name, start, time in children]
    token = _active.set([totals, stack])
    try:
        yield totals
    finally:
        _active.reset(token)
        name, start, children = stack[0]
        totals[name] = totals.get(name, 0.0) + time.perf_counter() - start - children


@contextlib.contextmanager
def stage(name: str):
    """Count the block's wall time (less its nested stages) under ``name``."""
    active = _active.get()
    if active is None:
        yield
        return
    totals, stack = active
    frame = [name, time.perf_counter(), 0.0]
    stack.append(frame)
    try:
        yield
    finally:
        stack.pop()
        elapsed = time.perf_counter() - frame[1]
        totals[name] = totals.get(name, 0.0) + elapsed - frame[2]
        stack[-1][2] += elapsed


def timed(name: str):
    """Decorator: every call of the function is the stage ``name``."""

    def wrap(func):
        @functools.wraps(func)
        def inner(*args, **kwargs):
            with stage(name):
                return func(*args, **kwargs)

        return inner

    return wrap
