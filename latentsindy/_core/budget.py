"""A discovery's time budget (``max_time``) and its progress lines.

``with budget(max_time, verbose):`` opens one; inside it :func:`expired` says whether
the time is spent, :func:`passed` records a step left out because of it (what was not
judged, said in the result's doubt), :func:`spent` does both for a step about to
start, and :func:`progress` prints which step is running
and how many hypotheses remain (with ``verbose``). Outside a budget nothing expires
and nothing is printed. Stage one's structure search checks the budget before every
neighbour it fits (a climbing step the deadline passes in is not taken) and fits no
adaptive priors once it is spent, the proposals before every alternative to stage one's
own structure, stage two before every hypothesis, every term-selection step and every
Levenberg-Marquardt iteration, so a call returns near its deadline with the best
system found so far. Stage one's training (a fixed number of steps, seconds on most
data), its starting structures and the posterior of the structure chosen always
complete; the structure search between the training's phases keeps the second phase's
expected time in reserve, starts a neighbour only where one at the last pace would end
in time, and the adaptive priors only where their first fit (up to ``EM_STEPS``
roughness searches, each at the Gaussian fits' pace) would (:func:`reserving`,
``spent(step, ahead)``). From the second phase on, the call keeps as much time again to
its end (:func:`before_a_phase`) for what runs whatever the budget: the chosen structure's
posterior, stage two's judgement of stage one's own structure, the step under way and
the result (whose checks that refit the chosen system are left out once the budget is
spent).

The deadline is a point on the monotonic clock, so a forked helper process
(:mod:`.parallel`) reads the same one. A helper's own records are lost with it, so what
it leaves out is also written to a page of memory shared across the fork
(:meth:`Budget.elsewhere`), and :func:`left_out` and :meth:`Budget.left_out` read both.
``discover_hidden`` flags a result where a step was left out in any process, naming
each; a call that left nothing out but ended past its deadline gets a note, not a doubt
(its judgement is complete).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import sys
import time
from contextvars import ContextVar
from dataclasses import dataclass, field, replace

from tqdm.auto import tqdm

from .doubt import Doubt


@dataclass
class Budget:
    max_time: float | None
    verbose: bool
    start: float = field(default_factory=time.monotonic)
    passed: list[str] = field(default_factory=list)
    reserve: float = 0.0  # seconds kept for work that runs whatever the budget
    closing: float = 0.0  # seconds kept for making the result (:func:`keep_for_closing`)
    owner: int = field(default_factory=os.getpid)
    # memory shared with forked helpers: the steps they left out, one per line
    shared: mmap.mmap | None = field(default=None, repr=False)
    # the shared memory's file (a memfd: Linux, the one platform with helpers), locked
    # around a helper's record (an outer and an inner map's helpers can write at once)
    lock_fd: int | None = field(default=None, repr=False)
    # what helpers left out, read from the shared memory when the budget closed
    seen_elsewhere: list[str] = field(default_factory=list)

    def __post_init__(self):
        if (self.max_time is not None and self.shared is None
                and hasattr(os, "memfd_create")):  # Linux, the one platform with helpers
            self.lock_fd = os.memfd_create("latentsindy-budget")
            os.ftruncate(self.lock_fd, _SHARED_BYTES)
            self.shared = mmap.mmap(self.lock_fd, _SHARED_BYTES)

    def close(self) -> None:
        """Keep what helpers left out, and release the shared memory and its file (the
        budget's block has ended)."""
        if self.shared is not None:
            self.seen_elsewhere = self.elsewhere()
            self.shared.close()
        if self.lock_fd is not None:
            os.close(self.lock_fd)
        self.shared = self.lock_fd = None

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def elsewhere(self) -> list[str]:
        """The steps forked helper processes left out, in the order first recorded."""
        if self.shared is None:
            return list(self.seen_elsewhere)
        text = self.shared[:].split(b"\0", 1)[0].decode("utf-8", "replace")
        return [line for line in text.split("\n") if line]

    def record_elsewhere(self, what: str) -> None:
        """Record ``what`` in the shared memory (a helper's record, under the lock).
        Where the page is full, a last line says that more was left out."""
        if self.shared is None:
            return
        what = " ".join(what.split())  # one line
        with _locked(self.lock_fd):
            steps = self.elsewhere()
            if what in steps or _MORE in steps:
                return
            line = (what + "\n").encode("utf-8")
            end = sum(len(s.encode("utf-8")) + 1 for s in steps)
            if end + len(line) + len(_MORE) + 2 > _SHARED_BYTES:
                line = (_MORE + "\n").encode("utf-8")
            self.shared[end:end + len(line)] = line

    def overran(self) -> bool:
        """Whether the deadline itself has passed (the time kept in reserve aside)."""
        return self.max_time is not None and self.elapsed() > self.max_time

    def left_out(self) -> str | None:
        """What was left out, here or in a helper, as text; None where nothing was
        (a call that ends in the time kept for its result, or past its deadline, having
        left nothing out, was judged in full)."""
        steps = self.passed + [s for s in self.elsewhere() if s not in self.passed]
        return "; ".join(steps) or None

    def expired(self) -> bool:
        return (self.max_time is not None
                and self.elapsed() + self.reserve + self.closing > self.max_time)


_SHARED_BYTES = 4096
_MORE = "more steps of the second process"

_active: ContextVar[Budget | None] = ContextVar("latentsindy_budget", default=None)


@contextlib.contextmanager
def budget(max_time: float | None, verbose: bool = False):
    """A budget of ``max_time`` wall seconds (None: no limit) for the block."""
    state = Budget(max_time, verbose)
    token = _active.set(state)
    try:
        yield state
    finally:
        _active.reset(token)
        state.close()


def stamped(result, state: Budget):
    """``result`` (a :class:`~latentsindy.HiddenDiscovery`) with the ``"time budget"``
    doubt where ``state``'s budget left a step out (in any process), naming each; with a
    note where it left nothing out but the call ended past its deadline (the judgement
    is complete: no doubt); else unchanged."""
    left = state.left_out()
    if left is not None:
        return replace(result, doubts=result.doubts + (Doubt(
            "time budget", f"the time budget (max_time={state.max_time:g} s) did not allow "
            f"the full judgement ({state.elapsed():.1f} s used); left out: {left}. The "
            "system shown is the best found by then. Raise max_time (--max-time on the "
            "command line), or leave it unset, for a full judgement"),))
    if state.overran():
        return replace(result, notes=result.notes + (
            f"max_time={state.max_time:g} s was passed ({state.elapsed():.1f} s used) while "
            "the result was made; nothing was left out: the judgement is complete",))
    return result


@contextlib.contextmanager
def _locked(fd: int):
    """An exclusive lock on the file ``fd`` for the block (a process's own, so it
    excludes a forked one)."""
    import fcntl  # fd is a memfd's, so this is Linux

    fcntl.lockf(fd, fcntl.LOCK_EX)
    try:
        yield
    finally:
        fcntl.lockf(fd, fcntl.LOCK_UN)


@contextlib.contextmanager
def reserving(seconds: float):
    """Inside the block the active budget counts as spent ``seconds`` early: time kept
    for what must still run after a step that checks it (stage one's second training
    phase after its structure search; a neighbour's fit, at the pace of the last ones,
    before the search starts it). Nothing outside a budget."""
    state = _active.get()
    if state is None:
        yield
        return
    before = state.reserve
    state.reserve = before + max(float(seconds), 0.0)
    try:
        yield
    finally:
        state.reserve = before


def keep_for_closing(seconds: float) -> None:
    """From now on the active budget counts as spent ``seconds`` early: time kept, to
    the end of the call, for what runs after the last step that checks it (the result
    and its checks, the step under way when the time ran out). Nothing outside a
    budget."""
    state = _active.get()
    if state is not None:  # the most any training of the call asked for
        state.closing = max(state.closing, float(seconds), 0.0)


@contextlib.contextmanager
def before_a_phase(seconds: float):
    """Inside the block ``seconds`` are kept for a phase that follows it whatever the
    budget (stage one's second training phase, at the first one's pace), and from now
    to the end of the call as much again (:func:`keep_for_closing`) for what follows
    that phase whatever the budget: the chosen structure's posterior, stage two's
    judgement of stage one's own structure, the step under way and the result (on
    Hindmarsh-Rose what ran past the deadline without it took 0.4-1.0 s, where the phase
    takes 1.7 s). Nothing outside a budget."""
    keep_for_closing(seconds)
    with reserving(seconds):
        yield


def expired() -> bool:
    """Whether the active budget is spent (never outside a budget)."""
    state = _active.get()
    return state is not None and state.expired()


def spent(step: str, ahead: float = 0.0) -> bool:
    """Whether the active budget is spent, or would be ``ahead`` seconds from now (a
    step that long would not end in time); if so, ``step`` is recorded as left out."""
    with reserving(ahead):
        if not expired():
            return False
    passed(step)
    return True


def left_out(step: str) -> bool:
    """Whether ``step`` was recorded as left out (by this process or a helper)."""
    state = _active.get()
    return state is not None and (step in state.passed or step in state.elsewhere())


def passed(what: str) -> None:
    """Record a step left out because the budget is spent (once per kind of step)."""
    state = _active.get()
    if state is None:
        return
    if what not in state.passed:
        if os.getpid() == state.owner:  # each step left out, once
            progress(f"left out for the time budget (max_time={state.max_time:g} s): "
                     f"{what}")
        state.passed.append(what)
    if os.getpid() != state.owner and state.shared is not None:
        state.record_elsewhere(what)  # for the process that opened the budget


def progress(message) -> None:
    """Print ``message`` (a str, or a function that returns it: made only when printed)
    with the time spent so far, when the budget is verbose."""
    state = _active.get()
    if state is not None and state.verbose:
        text = message() if callable(message) else message
        # above stage one's progress bar, where one is showing (tqdm redraws it below)
        tqdm.write(f"[latentsindy {state.elapsed():6.1f} s] {text}", file=sys.stderr)
