"""Threads and floating-point modes for stage one's small float32 arithmetic."""

import numpy as np
import pytest
import torch

from latentsindy._core.threads import flush_denormals, one_blas_thread, single_thread

# half of float32's smallest normal number: a denormal
_DENORMAL = np.float32(np.finfo(np.float32).tiny / 2)


def _times_one(value):
    """``value`` times one in float32 array arithmetic on this thread."""
    return (np.array([value], dtype=np.float32) * np.float32(1.0))[0]


def _cannot_flush():
    supported = torch.set_flush_denormal(True)
    torch.set_flush_denormal(False)
    return not supported


def test_a_denormal_survives_outside_the_block():
    assert _DENORMAL > 0
    assert _times_one(_DENORMAL) == _DENORMAL


@pytest.mark.skipif(_cannot_flush(), reason="this CPU cannot flush denormals")
def test_denormals_are_zero_inside_the_block_and_back_after():
    with flush_denormals():
        inside = _times_one(_DENORMAL)
        normal = _times_one(np.float32(1e-30))
    after = _times_one(_DENORMAL)
    assert inside == 0.0
    assert normal == np.float32(1e-30)  # normal numbers are untouched
    assert after == _DENORMAL


@pytest.mark.skipif(_cannot_flush(), reason="this CPU cannot flush denormals")
def test_the_mode_is_restored_when_the_block_raises():
    with pytest.raises(RuntimeError, match="inside"), flush_denormals():
        raise RuntimeError("inside")
    assert _times_one(_DENORMAL) == _DENORMAL


@pytest.mark.skipif(_cannot_flush(), reason="this CPU cannot flush denormals")
def test_a_thread_that_flushed_before_still_flushes_after():
    torch.set_flush_denormal(True)
    try:
        with flush_denormals():
            pass
        assert _times_one(_DENORMAL) == 0.0
    finally:
        torch.set_flush_denormal(False)
    assert _times_one(_DENORMAL) == _DENORMAL


def test_single_thread_restores_torch_threads():
    before = torch.get_num_threads()
    with single_thread():
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == before


def _pool_threads():
    """{library path: threads} of every thread pool threadpoolctl finds now, afresh."""
    from threadpoolctl import threadpool_info

    return {p["filepath"]: p["num_threads"] for p in threadpool_info()}


def test_single_thread_limits_every_thread_pool_and_restores_them():
    before = _pool_threads()
    assert before  # numpy's BLAS at least
    with single_thread():
        inside = _pool_threads()
    assert inside == dict.fromkeys(before, 1)  # the kept controller misses no library
    assert _pool_threads() == before


def test_one_blas_thread_is_restored_when_the_block_raises():
    before = _pool_threads()
    with pytest.raises(RuntimeError, match="inside"), one_blas_thread():
        assert set(_pool_threads().values()) == {1}
        raise RuntimeError("inside")
    assert _pool_threads() == before


def test_the_kept_controller_is_made_again_after_an_import(monkeypatch):
    """A library imported after the first call may bring a thread pool of its own: the
    controller is made again once modules have been imported, and only then."""
    import sys
    import types

    from latentsindy._core import threads

    with one_blas_thread():
        pass
    kept = threads._CONTROLLER[0]
    with one_blas_thread():
        pass
    assert threads._CONTROLLER[0] is kept
    monkeypatch.setitem(sys.modules, "_a_library_imported_later", types.ModuleType("x"))
    with one_blas_thread():
        pass
    assert threads._CONTROLLER[0] is not kept
