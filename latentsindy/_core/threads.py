"""Threads for small tensors (one for torch and one for the BLAS), and float32 denormals
flushed to zero on the training thread."""

from __future__ import annotations

import contextlib
import sys

import numpy as np
import torch
from threadpoolctl import ThreadpoolController

_CONTROLLER: list = []  # [controller, len(sys.modules) when it was made]


def one_blas_thread():
    """A context manager that runs the BLAS and OpenMP libraries on one thread inside its
    block (``threadpoolctl.threadpool_limits(1)``).

    ``threadpool_limits`` finds the loaded libraries anew at every call (2.6 ms, four
    times a discovery and again in its second process). The controller that finds them
    is kept, and made again only when modules have been imported since (a library that
    brings its own thread pool comes with an import).
    """
    if not _CONTROLLER or _CONTROLLER[1] != len(sys.modules):
        _CONTROLLER[:] = [ThreadpoolController(), len(sys.modules)]
    return _CONTROLLER[0].limit(limits=1)


@contextlib.contextmanager
def single_thread():
    """Run torch and the BLAS on one thread inside the block.

    Stage one's training step by hand and stage two's refinement work on small arrays,
    where threading costs more than it gains (torch 2.5x slower on 2 cores in the
    refinement, the BLAS 10-15% of stage two on Lorenz; with two BLAS threads the
    training step's small products and torch's element-wise kernels wait on each other,
    1.4 -> 20 ms a step).
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with one_blas_thread():
            yield
    finally:
        torch.set_num_threads(previous)


_HALF_TINY = np.array([np.finfo(np.float32).tiny / 2], dtype=np.float32)  # a denormal


def _flushing() -> bool:
    """Whether this thread flushes denormals now (torch has no getter: a denormal
    times one reads zero when it does)."""
    return bool((_HALF_TINY * np.float32(1.0))[0] == 0)


@contextlib.contextmanager
def flush_denormals():
    """Flush float denormals to zero on this thread inside the block (FTZ/DAZ).

    Stage one's training is float32 on one thread (:func:`single_thread`). A dead GELU
    unit's slope is ~exp(-x^2 / 2), and gradients through it fall below float32's
    smallest normal (1.2e-38), where x86 arithmetic takes a slow path: on prey-only
    Lotka-Volterra over 20,000 samples a decoder convolution's backward product ran
    at 600 us instead of ~100 us, for values that cannot move a parameter (Adam's
    steps from them are ~1e-33). Flushed, they are zero. Where the CPU cannot flush
    (``torch.set_flush_denormal`` returns False) nothing changes. Afterwards the
    thread keeps denormals again, unless it flushed them before the block.
    """
    before = _flushing()
    flushing = torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if flushing and not before:
            torch.set_flush_denormal(False)
