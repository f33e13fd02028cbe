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
(:mod:`.parallel`) reads the same one. What a helper records is lost with it, but that
it recorded a step is not: a byte of memory shared across the fork says so
(:meth:`Budget.cut_elsewhere`). ``discover_hidden`` flags a result where a step was left
out in any process, or where the call ran past its deadline, with what this process
recorded.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import sys
import time
from contextvars import ContextVar
from dataclasses import dataclass, field

from tqdm.auto import tqdm


@dataclass
class Budget:
    max_time: float | None
    verbose: bool
    start: float = field(default_factory=time.monotonic)
    passed: list[str] = field(default_factory=list)
    reserve: float = 0.0  # seconds kept for work that runs whatever the budget
    closing: float = 0.0  # seconds kept for making the result (:func:`keep_for_closing`)
    owner: int = field(default_factory=os.getpid)
    # one byte shared with forked helpers: set where a helper left a step out
    shared: mmap.mmap | None = field(default=None, repr=False)

    def __post_init__(self):
        if self.max_time is not None and self.shared is None:
            self.shared = mmap.mmap(-1, 1)  # anonymous, so shared across fork

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def cut_elsewhere(self) -> bool:
        """Whether a forked helper process left a step out (what, it could not say)."""
        return self.shared is not None and self.shared[0] == 1

    def overran(self) -> bool:
        """Whether the deadline itself has passed (the time kept in reserve aside)."""
        return self.max_time is not None and self.elapsed() > self.max_time

    def left_out(self) -> str | None:
        """What was left out, here or in a helper, as text; None where nothing was and
        the deadline has not passed (a call that ends in the time kept for its result,
        having left nothing out, is not flagged)."""
        steps = self.passed + (["steps of the second process"] if self.cut_elsewhere() else [])
        if steps or self.overran():
            return "; ".join(steps) or "nothing, but the call ran past it"
        return None

    def expired(self) -> bool:
        return (self.max_time is not None
                and self.elapsed() + self.reserve + self.closing > self.max_time)


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
    """Whether ``step`` was recorded as left out (by this process)."""
    state = _active.get()
    return state is not None and step in state.passed


def passed(what: str) -> None:
    """Record a step left out because the budget is spent (once per kind of step)."""
    state = _active.get()
    if state is None:
        return
    if what not in state.passed:
        state.passed.append(what)
    if os.getpid() != state.owner and state.shared is not None:
        state.shared[0] = 1  # for the process that opened the budget


def progress(message) -> None:
    """Print ``message`` (a str, or a function that returns it: made only when printed)
    with the time spent so far, when the budget is verbose."""
    state = _active.get()
    if state is not None and state.verbose:
        text = message() if callable(message) else message
        # above stage one's progress bar, where one is showing (tqdm redraws it below)
        tqdm.write(f"[latentsindy {state.elapsed():6.1f} s] {text}", file=sys.stderr)
