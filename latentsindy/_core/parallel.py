"""A second core for the independent pieces of one discovery: a forked helper process.

A discovery runs on one thread (its arrays are small, see :mod:`.threads`), so on a
machine with two or more cores the others sit idle. Pieces that do not depend on one
another (the held-out folds of a score, the candidates finished after their first fit)
can run in a forked copy of the process: it shares the parent's memory as it was at the
fork, so no input is sent, and each result comes back pickled. :func:`forked_map` runs a
function over the items in the parent and in one helper, each taking the next item from
a shared queue, and returns the results in order: the same values as a loop, since
each item is computed the same way wherever it runs (on one torch thread in both).

The helper is used only where it is safe and pays (:func:`available`): on Linux (fork),
from the main thread (so two maps never race; a fork copies only the calling thread,
and the helper touches nothing the others hold), with torch on one thread, a second
core in the process's affinity mask, at least two items, and not where switched off
(:func:`enable`:
``discover_many``'s workers and the benchmarks' processes each have a core of their
own; :func:`map_on` keeps it off for a CUDA device, whose context does not survive a
fork, and no helper is forked once this process has a CUDA context at all; a user
running calls side by side sets ``LATENTSINDY_SECOND_PROCESS=0``).
A map inside an item of another (a hypothesis's held-out folds, its term selection's
refits) runs as a loop while the other process of the outer map works; once that one
has nothing left (the parent waits on the helper's last item, or the helper has
finished its share while the parent's last item runs), the inner map forks a helper
of its own, so the idle core takes inner items: one begun then forks at once, one
already looping forks for the items it has left. Two processes work at any time, and
maps nest at most two deep.
A map whose items are expected to take less than ``FORK_WORTH`` in all, at the pace of
the last map from the same call site in this process, runs as a loop, and shares its
items left once they are expected to take longer (:func:`_loop`): a helper costs more
than it saves on a few short items. A helper that has sent its results is reaped later
(:func:`_reap`), so that its exit does not hold up the parent.
Whatever goes wrong in the helper (an exception, a result that does not pickle, a
crash, no answer in ``patience`` seconds) costs time only: the parent computes the
helper's items itself, so an error is raised by the parent, from the first item (in
the parent's order of work) that fails there.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import mmap
import os
import pickle
import select
import signal
import struct
import sys
import threading
import time
import warnings

import numpy as np
import torch

from .timing import stage

_WAIT_STAGE = "waiting for the second process"
_MAX_ITEMS = 1024  # the queue's item indices fit in one atomic pipe write (PIPE_BUF)
_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_MAX_DEPTH = 2  # an outer map and one inner map fork; a third level loops
_PARENT_IDLE, _HELPER_DONE = 0, 1  # a map's shared flags: the parent waits, the helper ended
_enabled = True
# A map whose items are expected to take less than this in all (at the pace of its last
# run from the same call site) runs as a loop, and goes on to fork only if it runs
# longer. A helper costs the parent 10-15 ms (the fork of a process that holds torch,
# 500 MB; the helper's results, its exit out of the way) and more in pages copied on
# write after it, both processes compete for the memory bus, and the most it can save
# is half the map: prey-only Lotka-Volterra's maps of 30-40 ms (held-out folds, checks)
# were slower forked than looped, and its whole call 0-15% slower with the helper
# than without (2026-12-03)
FORK_WORTH = 0.1
_SECONDS_PER_ITEM: dict = {}  # per call site (the mapped function's code): the last pace
_depth = 0  # forked maps this process is inside, as their parent or their helper
_flags: mmap.mmap | None = None  # the innermost one's shared flags
_side = _PARENT_IDLE  # which of its flags is this process's own: the other is its partner


def enable(flag: bool) -> bool:
    """Allow (True) or forbid (False) the helper process in this process; returns the
    previous setting."""
    global _enabled
    previous, _enabled = _enabled, bool(flag)
    return previous


def available(n_items: int) -> bool:
    """Whether :func:`forked_map` would use a helper for ``n_items`` items."""
    if (not _enabled or not 2 <= n_items <= _MAX_ITEMS or sys.platform != "linux"
            or not _partner_idle()
            or os.environ.get("LATENTSINDY_SECOND_PROCESS", "1") == "0"
            or threading.current_thread() is not threading.main_thread()
            or torch.get_num_threads() != 1
            # a CUDA context does not survive a fork: once one exists (a fit on a GPU),
            # even CPU-only pieces (stage one's structure search) stay in this process
            or torch.cuda.is_initialized()):
        return False
    return len(os.sched_getaffinity(0)) >= 2


def _partner_idle() -> bool:
    """Outside any forked map, True; inside one (an inner map), whether the other
    process of the innermost map has nothing left to do, and nesting may go deeper."""
    if _depth == 0:
        return True
    if _depth >= _MAX_DEPTH or _flags is None:
        return False
    partner = _HELPER_DONE if _side == _PARENT_IDLE else _PARENT_IDLE
    return _flags[partner] == 1


def map_on(device, func, items, cost=None) -> list:
    """:func:`forked_map` on a CPU ``device``; a plain loop on any other."""
    if torch.device(device).type == "cpu":
        return forked_map(func, items, cost=cost)
    return [func(x) for x in items]


def forked_map(func, items, patience: float = 60.0, cost=None, paced=True) -> list:
    """``[func(x) for x in items]``, shared with a forked helper when :func:`available`.

    ``func`` needs no pickling (the helper is a fork); its results must pickle to come
    back (those that do not are recomputed by the parent). The parent waits for the
    helper's last item at most ``patience`` seconds plus 20 times its own share's time.
    ``cost`` (a number per item, optional) is what each item is expected to take: the
    costliest are handed out first (the longest-first rule, so that neither process is
    left with a long item at the end while the other waits); the results, and each one's
    value, are the same whatever the order. ``paced=False``: the caller has judged the
    map worth a helper itself (the structure search's own pace), and the size rule
    (``FORK_WORTH``) does not apply.
    """
    items = list(items)
    if cost is not None:
        cost = [float(c) for c in cost]
        if len(cost) != len(items):
            raise ValueError(f"forked_map: {len(cost)} costs for {len(items)} items.")
    if not available(len(items)) or (paced and _too_small(func, len(items))):
        return _loop(func, items, patience, cost)
    return _forked(func, items, patience, cost)


def _forked(func, items, patience, cost) -> list:
    """:func:`forked_map` with a helper (:func:`available` said so)."""
    queue = list(range(len(items)))
    if cost is not None:
        queue.sort(key=lambda k: -cost[k])  # stable: equal costs keep their order
    opened = []
    try:
        queue_r, queue_w = os.pipe()
        opened += [queue_r, queue_w]
        result_r, result_w = os.pipe()
        opened += [result_r, result_w]
        os.set_blocking(queue_r, False)  # every item is queued before the fork
        os.write(queue_w, b"".join(struct.pack("i", k) for k in queue))
        os.close(queue_w)
        opened.remove(queue_w)
        flags = mmap.mmap(-1, 2)  # shared with the helper: zero, zero
        pid = _fork()
    except OSError:  # no pipe or no process to be had: the loop
        for fd in opened:
            os.close(fd)
        return [func(x) for x in items]
    if pid == 0:
        _helper(func, items, queue_r, result_r, result_w, flags)  # never returns
    os.close(result_w)
    return _share(func, items, queue, pid, queue_r, result_r, patience, flags)


def _too_small(func, n_items) -> bool:
    """Whether the last map of ``func`` (the same code: the same call site) took so
    little per item that ``n_items`` of them are expected to take less than
    ``FORK_WORTH``: too little for a helper to pay."""
    per_item = _SECONDS_PER_ITEM.get(getattr(func, "__code__", None))
    return per_item is not None and per_item * n_items < FORK_WORTH


def _remember(func, seconds, n_items):
    key = getattr(func, "__code__", None)
    if key is not None and n_items:
        _SECONDS_PER_ITEM[key] = seconds / n_items


def _loop(func, items, patience, cost) -> list:
    """``[func(x) for x in items]`` where no helper was to be had, or where the items
    were expected to be too small for one (:func:`_too_small`). Before each item,
    the items left are shared if they are expected to take ``FORK_WORTH`` or more at
    the pace so far and :func:`available` now says yes: inside another map (an inner
    map begun while that map's other process was busy), as soon as that process has
    nothing left to do, so that its core does not idle while this loop runs on."""
    out, start = [], time.perf_counter()
    for k, x in enumerate(items):
        if k:
            left = len(items) - k
            pace = (time.perf_counter() - start) / k
            if pace * left >= FORK_WORTH and available(left):
                _remember(func, time.perf_counter() - start, k)
                return out + _forked(func, items[k:], patience,
                                     None if cost is None else cost[k:])
        out.append(func(x))
    _remember(func, time.perf_counter() - start, len(items))
    return out


def shared_values(n: int) -> np.ndarray:
    """``n`` floats (NaN at first) that the parent and the helper of a later
    :func:`forked_map` both read and write (anonymous shared memory survives the fork):
    what one process has found so far, for the other to use while it works. An aligned
    float is written whole, so a reader sees either NaN or the value."""
    if n == 0:
        return np.empty(0)
    values = np.frombuffer(mmap.mmap(-1, 8 * n), dtype=np.float64)
    values[:] = np.nan
    return values


def _fork():
    """Fork with SIGINT blocked around it (the child must not meet a Ctrl-C before it
    is in :func:`_helper`, which ignores it; the parent gets it right after)."""
    sys.stdout.flush()
    sys.stderr.flush()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    parent = os.getpid()
    try:
        with warnings.catch_warnings():  # Python >= 3.12 warns on forking with threads
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
        if pid == 0:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            _die_with_parent(parent)
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)
    return pid


def _die_with_parent(parent):
    """In a helper: be killed when the process that forked it ends (Linux's
    PR_SET_PDEATHSIG), so that an inner map's helper never outlives the outer map's
    helper that forked it (stopped at its patience, or killed by the system), nor
    holds the outer map's result pipe open after it."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL))
    if os.getppid() != parent:  # ``parent`` ended before the request was made
        os._exit(0)


def _share(func, items, queue, pid, queue_r, result_r, patience, flags):
    """The parent's side: its own items, then the helper's results."""
    global _depth, _flags, _side
    outer = _depth, _flags, _side
    _depth, _flags, _side = _depth + 1, flags, _PARENT_IDLE
    results, helper = {}, {}
    try:
        start = time.perf_counter()
        while (k := _take(queue_r)) is not None:
            results[k] = func(items[k])
        own = time.perf_counter() - start
        flags[_PARENT_IDLE] = 1  # the helper's inner maps may fork from now on
        with stage(_WAIT_STAGE):
            helper = _collect(pid, result_r, patience + 20.0 * own)
        pid = None  # reaped (or stopped) by _collect
    finally:
        _depth, _flags, _side = outer
        os.close(queue_r)
        os.close(result_r)
        if pid is not None:  # the parent's own item raised: stop the helper
            _stop(pid)
    for k in queue:  # the parent's order of work: an error comes from the first to fail
        if k not in results:
            results[k] = helper[k] if k in helper else func(items[k])
    # two processes worked, from the fork to the helper's results: twice that time
    _remember(func, 2.0 * (time.perf_counter() - start), len(items))
    return [results[k] for k in range(len(items))]


def _take(fd):
    """The next item index from the queue, or None when it is empty."""
    try:
        data = os.read(fd, 4)
    except BlockingIOError:
        return None
    return struct.unpack("i", data)[0] if len(data) == 4 else None


def _helper(func, items, queue_r, result_r, result_w, flags):
    """The helper's life: take items until the queue is empty (or one fails, or the
    parent is gone), send the results, exit without the parent's exit handlers."""
    global _depth, _flags, _side
    try:
        os.close(result_r)
        _depth, _flags, _side = _depth + 1, flags, _HELPER_DONE
        parent = os.getppid()
        torch.set_num_threads(1)  # as in the parent (available() asks for it)
        done = {}
        while os.getppid() == parent and (k := _take(queue_r)) is not None:
            try:
                done[k] = func(items[k])
            except BaseException:  # noqa: BLE001 - the parent recomputes it and raises
                break
        flags[_HELPER_DONE] = 1  # the parent's inner maps may fork from now on
        try:
            payload = pickle.dumps(done, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception:  # noqa: BLE001 - an unpicklable result: the parent does all
            payload = b""
        view = memoryview(payload)
        while view:
            view = view[os.write(result_w, view):]
        # the end of the results: without it the parent would read on until this
        # process's exit had released its whole address space (10 ms and more)
        os.close(result_w)
        reap_helpers()  # this helper's own helpers: os._exit runs no exit handlers
    finally:
        os._exit(0)


def _collect(pid, fd, timeout):
    """The helper's results ({index: result}; {} if it failed or ran out of time); the
    helper is reaped either way."""
    chunks, deadline = [], time.monotonic() + timeout
    poller = select.poll()
    poller.register(fd, select.POLLIN | select.POLLHUP)
    while True:
        left = deadline - time.monotonic()
        if left <= 0 or not poller.poll(left * 1000.0):
            _stop(pid)
            return {}
        data = os.read(fd, 1 << 20)
        if not data:
            break
        chunks.append(data)
    _reap(pid, wait=False)
    try:
        return pickle.loads(b"".join(chunks)) if chunks else {}
    except Exception:  # noqa: BLE001 - a truncated payload (the helper died)
        return {}


def _stop(pid):
    """Kill the helper and reap it."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)
    _reap(pid)


# helpers that sent their results and may still be exiting (a forked child starts with
# none: its parent's helpers are not its children). Reaped by pid: code that reaps every
# child itself (os.wait(), SIGCHLD ignored) could let a pid here be reused before it is
# waited for; this module's helpers exit right after their results, so the window is
# the length of an exit.
_exiting: list[int] = []
os.register_at_fork(after_in_child=_exiting.clear)


def _reap(pid, wait=True):
    """Reap the helper ``pid``; without ``wait``, only if it has ended, else later (at
    the next reaping, or at the interpreter's exit): a helper that has sent its results
    is done, and its exit (releasing a copy of the parent's address space) need not
    hold up the parent."""
    for other in list(_exiting):
        with contextlib.suppress(ChildProcessError):  # SIGCHLD ignored: reaped already
            if os.waitpid(other, os.WNOHANG)[0] == 0:
                continue
        _exiting.remove(other)
    with contextlib.suppress(ChildProcessError):
        if os.waitpid(pid, 0 if wait else os.WNOHANG)[0] == 0:
            _exiting.append(pid)


@atexit.register
def reap_helpers():
    """Wait for the helpers that have sent their results and are still exiting."""
    while _exiting:
        with contextlib.suppress(ChildProcessError):
            os.waitpid(_exiting.pop(), 0)
