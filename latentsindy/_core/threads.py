"""Threads for small tensors: one for torch and one for the BLAS."""

from __future__ import annotations

import contextlib

import torch
from threadpoolctl import threadpool_limits


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
        with threadpool_limits(1):
            yield
    finally:
        torch.set_num_threads(previous)
