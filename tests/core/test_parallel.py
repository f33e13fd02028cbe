"""The forked helper: the same results as a loop, in order, whatever happens to it."""

import os
import time

import pytest

from latentsindy._core import parallel
from latentsindy._core.parallel import available, forked_map
from latentsindy._core.timing import recording

PARENT = os.getpid()
needs_helper = pytest.mark.skipif(not available(2), reason="needs Linux and two cores")


def slow_square(x):
    time.sleep(0.05)
    return x * x, os.getpid()


@needs_helper
def test_results_are_the_loops_in_order_and_both_processes_work():
    out = forked_map(slow_square, range(12))
    assert [v for v, _ in out] == [x * x for x in range(12)]
    pids = {pid for _, pid in out}
    assert PARENT in pids and len(pids) == 2  # the helper took some


@needs_helper
def test_an_error_is_raised_by_the_parent_whichever_process_met_it():
    def fails_on_three(x):
        time.sleep(0.02)
        if x == 3:
            raise ValueError(f"item {x} failed")
        return x

    for _ in range(3):  # item 3 lands in either process
        with pytest.raises(ValueError, match="item 3 failed"):
            forked_map(fails_on_three, range(8))
    assert [v for v, _ in forked_map(slow_square, [1, 2])] == [1, 4]  # usable after


@needs_helper
def test_results_that_do_not_pickle_are_computed_by_the_parent():
    def closure(x):
        time.sleep(0.02)
        return lambda: x + 1  # a local lambda does not pickle

    out = forked_map(closure, range(6))
    assert [f() for f in out] == [x + 1 for x in range(6)]


@needs_helper
def test_a_helper_that_dies_costs_time_not_results():
    def dies_in_helper(x):
        time.sleep(0.02)
        if os.getpid() != PARENT:
            os._exit(3)
        return -x

    assert forked_map(dies_in_helper, range(6)) == [-x for x in range(6)]


@needs_helper
def test_a_helper_that_hangs_is_stopped_after_its_patience():
    def hangs_in_helper(x):
        if os.getpid() != PARENT:
            time.sleep(60)
        time.sleep(0.02)
        return x

    start = time.perf_counter()
    assert forked_map(hangs_in_helper, range(4), patience=0.5) == list(range(4))
    assert time.perf_counter() - start < 10


@needs_helper
def test_nested_maps_and_a_switched_off_helper_run_as_loops():
    def inner(x):
        return forked_map(lambda y: os.getpid(), range(3))

    for pids in forked_map(inner, range(4)):
        assert len(set(pids)) == 1  # each inner map ran in one process
    previous = parallel.enable(False)
    try:
        assert not available(2)
        assert {pid for _, pid in forked_map(slow_square, range(6))} == {PARENT}
    finally:
        parallel.enable(previous)
    assert available(2)


@needs_helper
def test_the_environment_switches_the_helper_off(monkeypatch):
    monkeypatch.setenv("LATENTSINDY_SECOND_PROCESS", "0")
    assert not available(2)
    assert {pid for _, pid in forked_map(slow_square, range(4))} == {PARENT}
    monkeypatch.setenv("LATENTSINDY_SECOND_PROCESS", "1")
    assert available(2)


def test_too_few_items_need_no_helper():
    assert not available(1) and not available(0)
    assert forked_map(slow_square, [3]) == [(9, PARENT)]
    assert forked_map(slow_square, []) == []


@needs_helper
def test_the_parents_wait_is_a_stage_of_its_own():
    def slow_in_helper(x):
        time.sleep(0.5 if os.getpid() != PARENT else 0.05)
        return x

    with recording() as times:
        assert forked_map(slow_in_helper, range(4)) == list(range(4))
    # the helper takes an item while the parent works on its first (0.05 s) and keeps
    # it for 0.5 s: the parent, done with the rest, waits for it, and says so
    assert times["waiting for the second process"] > 0.2
