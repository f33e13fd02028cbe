"""The forked helper: the same results as a loop, in order, whatever happens to it.

Which process takes which item is a race; the tests that need the helper to take one
make the parent's items wait (up to 10 s) for a file the helper writes when it starts
its first item.
"""

import os
import signal
import sys
import time

import pytest
import torch

from latentsindy._core import parallel
from latentsindy._core.parallel import available, forked_map, map_on
from latentsindy._core.timing import recording

PARENT = os.getpid()
needs_two_cores = pytest.mark.skipif(
    sys.platform != "linux" or len(os.sched_getaffinity(0)) < 2,
    reason="the helper needs Linux and two cores")


@pytest.fixture(autouse=True)
def one_torch_thread():
    """The helper is used with torch on one thread only (as in a discovery)."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture
def started(tmp_path):
    """A marker the helper writes as it starts an item; ``started.wait()`` blocks the
    parent until then."""
    path = tmp_path / "helper-started"

    class Marker:
        def mark(self):
            if os.getpid() != PARENT:
                path.touch()

        def wait(self):
            if os.getpid() == PARENT:
                deadline = time.monotonic() + 10
                while not path.exists() and time.monotonic() < deadline:
                    time.sleep(0.005)

        def seen(self):
            return path.exists()

    return Marker()


def children():
    """This process's child processes (Linux's /proc; other tests may leave some, such as
    joblib's workers)."""
    found = set()
    for task in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{task}/children") as fh:
            found |= {int(p) for p in fh.read().split()}
    return found


@pytest.fixture(autouse=True)
def every_map_may_fork(monkeypatch):
    """A helper for every map, however short its items (the size rule has tests of its
    own), and no memory of earlier maps' pace."""
    monkeypatch.setattr(parallel, "FORK_WORTH", 0.0)
    monkeypatch.setattr(parallel, "_SECONDS_PER_ITEM", {})


@pytest.fixture
def no_helper_left():
    """Asserts that every helper started in the test is gone (and reaped) at its end,
    once those that sent their results have exited."""
    before = children()
    yield
    parallel.reap_helpers()
    assert children() <= before


@needs_two_cores
def test_results_are_the_loops_in_order_and_both_processes_work(started, no_helper_left):
    def square(x):
        started.mark()
        started.wait()
        return x * x, os.getpid()

    out = forked_map(square, range(12))
    assert [v for v, _ in out] == [x * x for x in range(12)]
    assert len({pid for _, pid in out} | {PARENT}) == 2  # the helper's came back


@needs_two_cores
def test_the_costliest_items_are_handed_out_first(tmp_path, no_helper_left):
    log = tmp_path / "order"

    def record(x):
        with open(log, "a") as fh:  # one short append per item: whole lines
            fh.write(f"{x}\n")
        time.sleep(0.1)  # far longer than a take and a write: the log keeps queue order
        return -x

    cost = [1, 5, 2, 9, 0, 3]
    assert forked_map(record, range(6), cost=cost) == [-x for x in range(6)]
    taken = [int(line) for line in log.read_text().split()]
    assert sorted(taken) == list(range(6))
    # both processes take from the front of one queue ordered 3, 1, 5, 2, 0, 4: the two
    # costliest are the first two taken (in either order), the cheapest among the last
    assert set(taken[:2]) == {3, 1}
    assert 4 in taken[-2:]
    with pytest.raises(ValueError, match="2 costs for 3 items"):
        forked_map(record, range(3), cost=[1, 2])


@needs_two_cores
def test_an_error_is_raised_by_the_parent_whichever_process_met_it(started, no_helper_left):
    def fails_on_three(x):
        started.mark()
        started.wait()
        if x == 3:
            raise ValueError(f"item {x} failed")
        return x

    for _ in range(3):  # item 3 lands in either process
        with pytest.raises(ValueError, match="item 3 failed"):
            forked_map(fails_on_three, range(8))
        assert started.seen()
    assert forked_map(lambda x: x + 1, [1, 2]) == [2, 3]  # usable after


@needs_two_cores
def test_results_that_do_not_pickle_are_computed_by_the_parent(started):
    def closure(x):
        started.mark()
        started.wait()
        return lambda: x + 1  # a local lambda does not pickle

    out = forked_map(closure, range(6))
    assert started.seen()
    assert [f() for f in out] == [x + 1 for x in range(6)]


@needs_two_cores
def test_a_helper_that_dies_costs_time_not_results(started, no_helper_left):
    def dies_in_helper(x):
        started.mark()
        if os.getpid() != PARENT:
            os._exit(3)
        started.wait()
        return -x

    assert forked_map(dies_in_helper, range(6)) == [-x for x in range(6)]
    assert started.seen()


@needs_two_cores
def test_a_helper_that_hangs_is_stopped_after_its_patience(started, no_helper_left):
    def hangs_in_helper(x):
        started.mark()
        if os.getpid() != PARENT:
            time.sleep(60)
        started.wait()
        return x

    begin = time.perf_counter()
    assert forked_map(hangs_in_helper, range(4), patience=0.5) == list(range(4))
    assert time.perf_counter() - begin < 10
    assert started.seen()


@needs_two_cores
def test_the_parents_wait_is_a_stage_of_its_own(started):
    def slow_in_helper(x):
        started.mark()
        if os.getpid() != PARENT:
            time.sleep(0.5)
        started.wait()
        return x

    with recording() as times:
        assert forked_map(slow_in_helper, range(2)) == [0, 1]
    # the parent's item waits until the helper has taken the other one, which then
    # takes 0.5 s more: the parent waits for it, and says so
    assert times["waiting for the second process"] > 0.3


def _wait_for(condition, seconds=10.0):
    deadline = time.monotonic() + seconds
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.005)
    return condition()


@needs_two_cores
def test_inner_maps_loop_while_the_other_process_works(tmp_path, no_helper_left):
    def outer(x):
        (tmp_path / f"began-{x}").touch()
        _wait_for(lambda: all((tmp_path / f"began-{y}").exists() for y in range(2)))
        pids = forked_map(lambda y: os.getpid(), range(3))  # the other is mid-item
        (tmp_path / f"ended-{x}").touch()
        _wait_for(lambda: all((tmp_path / f"ended-{y}").exists() for y in range(2)))
        return pids, os.getpid()

    out = forked_map(outer, range(2))
    assert len({pid for _, pid in out}) == 2  # one item in each process
    for pids, pid in out:
        assert pids == [pid] * 3  # each inner map ran as a loop in its own process


@needs_two_cores
def test_an_inner_map_takes_the_idle_core(tmp_path, no_helper_left):
    def outer(x):
        if x == 0:
            return "quick", os.getpid()
        # the long item: once the other process has nothing left, its core is free
        assert _wait_for(parallel._partner_idle)

        def inner(y):
            (tmp_path / f"inner-{y}-{os.getpid()}").touch()
            _wait_for(lambda: len(list(tmp_path.glob("inner-*"))) >= 2)
            assert not available(2)  # a third level loops
            return y * y, os.getpid()

        return forked_map(inner, range(4)), os.getpid()

    for _ in range(3):  # the long item lands in either process
        for path in tmp_path.glob("inner-*"):
            path.unlink()
        quick, long = forked_map(outer, range(2))
        assert quick[0] == "quick"
        inner, pid = long
        assert [v for v, _ in inner] == [0, 1, 4, 9]  # in order, the loop's values
        assert pid in {p for _, p in inner} and len({p for _, p in inner}) == 2


@needs_two_cores
def test_a_looping_inner_map_shares_its_items_left_once_a_core_is_free(tmp_path,
                                                                       no_helper_left):
    def inner(y):
        if y == 0:  # begun while the other process works; it finishes meanwhile
            (tmp_path / "inner-began").touch()
            assert _wait_for(parallel._partner_idle)
        else:  # each of the items left waits until both processes have taken one
            (tmp_path / f"inner-{y}-{os.getpid()}").touch()
            _wait_for(lambda: len(list(tmp_path.glob("inner-*-*"))) >= 2)
        return y * y, os.getpid()

    def outer(x):
        if x == 0:  # ends once the other item's inner map has begun, as a loop
            assert _wait_for(lambda: (tmp_path / "inner-began").exists())
            return "quick", os.getpid()
        return forked_map(inner, range(4)), os.getpid()

    quick, (found, pid) = forked_map(outer, range(2))
    assert quick[1] != pid  # the two items ran in the two processes
    assert [v for v, _ in found] == [0, 1, 4, 9]  # in order, the loop's values
    assert found[0][1] == pid  # the first inner item in the loop
    left = {p for _, p in found[1:]}
    assert pid in left and len(left) == 2  # the items left: in two processes


def _alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split()[2] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


@needs_two_cores
def test_an_inner_helper_dies_with_the_helper_that_forked_it(started, tmp_path,
                                                             no_helper_left):
    def inner(y):
        (tmp_path / f"inner-{os.getpid()}").touch()
        time.sleep(5.0)
        return y

    def outer(x):
        if os.getpid() == PARENT:
            started.wait()
            return "parent"
        started.mark()
        assert _wait_for(parallel._partner_idle)
        helper = os.getpid()
        if os.fork() == 0:  # stands in for the system killing the helper mid-item
            time.sleep(0.5)
            os.kill(helper, signal.SIGKILL)
            os._exit(0)
        return forked_map(inner, range(2))

    begin = time.perf_counter()
    assert forked_map(outer, range(2)) == ["parent", "parent"]  # the parent redid it
    # the inner map's helper was killed with the helper, which held the outer map's
    # result pipe: the parent did not wait for its 5-s item
    assert time.perf_counter() - begin < 3.0
    inner_pids = {int(p.name.split("-")[1]) for p in tmp_path.glob("inner-*")}
    assert len(inner_pids) == 2  # the helper and its own helper each took an item
    assert _wait_for(lambda: not any(_alive(pid) for pid in inner_pids), 2.0)


@needs_two_cores
def test_the_switches_and_the_conditions(monkeypatch):
    assert available(2)
    previous = parallel.enable(False)
    try:
        assert not available(2)
        assert forked_map(lambda x: os.getpid(), range(4)) == [PARENT] * 4
    finally:
        parallel.enable(previous)
    monkeypatch.setenv("LATENTSINDY_SECOND_PROCESS", "0")
    assert not available(2)
    monkeypatch.setenv("LATENTSINDY_SECOND_PROCESS", "1")
    assert available(2)
    torch.set_num_threads(2)  # the helper's arithmetic would differ from the loop's
    assert not available(2)
    torch.set_num_threads(1)
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: True)  # no fork after CUDA
    assert not available(2)
    monkeypatch.setattr(torch.cuda, "is_initialized", lambda: False)
    assert not available(1) and not available(0) and not available(parallel._MAX_ITEMS + 1)
    assert map_on("meta", lambda x: os.getpid(), range(4)) == [PARENT] * 4


def test_too_few_items_need_no_helper():
    assert forked_map(lambda x: (x * x, os.getpid()), [3]) == [(9, PARENT)]
    assert forked_map(lambda x: x, []) == []


@needs_two_cores
def test_helpers_that_sent_their_results_are_reaped_later(no_helper_left):
    """The parent reads the helper's results to their end and goes on; the helper's
    exit is reaped later (at the next map, or by ``reap_helpers``)."""
    helpers = set()
    for _ in range(3):
        out = forked_map(lambda x: (x + 1, os.getpid()), range(64))
        assert [v for v, _ in out] == list(range(1, 65))
        helpers |= {pid for _, pid in out} - {PARENT}
        # every helper that came back is reaped or kept to be: none is lost
        assert all(pid in parallel._exiting or pid not in children() for pid in helpers)
    parallel.reap_helpers()
    assert not helpers & children()


@needs_two_cores
def test_a_map_known_to_be_short_runs_as_a_loop(monkeypatch, started, no_helper_left):
    monkeypatch.setattr(parallel, "FORK_WORTH", 1.0)  # a fork is far quicker than this

    def quick(x):
        return os.getpid()

    forked_map(quick, range(4))  # the first map from here: a helper, its pace kept
    assert parallel._SECONDS_PER_ITEM[quick.__code__] < 1.0 / 4
    assert forked_map(quick, range(4)) == [PARENT] * 4  # expected 4 x pace < 1 s
    # more items than the pace allows for in 1 s: worth a helper again
    many = int(1.0 / parallel._SECONDS_PER_ITEM[quick.__code__]) + 64
    assert parallel._too_small(quick, 4) and not parallel._too_small(quick, many)

    def judged(x):  # a caller that judged the map itself: a helper whatever the pace
        started.mark()
        started.wait()  # the parent's items wait until the helper has taken one
        return os.getpid()

    parallel._SECONDS_PER_ITEM[judged.__code__] = 1e-6
    assert parallel._too_small(judged, 4)
    pids = set(forked_map(judged, range(4), paced=False))
    assert len(pids | {PARENT}) == 2  # the helper's items came back (it may take all)


@needs_two_cores
def test_a_loop_that_runs_longer_than_expected_shares_what_is_left(monkeypatch,
                                                                   no_helper_left):
    monkeypatch.setattr(parallel, "FORK_WORTH", 0.1)

    def slow(x):
        time.sleep(0.06)
        return x * x, os.getpid()

    parallel._SECONDS_PER_ITEM[slow.__code__] = 1e-4  # last time it was quick
    out = forked_map(slow, range(8))
    assert [v for v, _ in out] == [x * x for x in range(8)]  # the loop's, in order
    assert out[0][1] == PARENT  # the first item in the loop; at 0.06 s an item, the
    assert len({pid for _, pid in out}) == 2  # seven left are worth a helper
    assert 0.05 < parallel._SECONDS_PER_ITEM[slow.__code__] < 1.0  # the pace now
