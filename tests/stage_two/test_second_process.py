"""Stage two's independent pieces on a second core give the same discovery, digit for
digit, as one process alone."""

import os
import sys
import time
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import pysindy as ps
import pytest

from latentsindy import discover_hidden, systems
from latentsindy._core import parallel
from latentsindy._core.threads import single_thread
from latentsindy._stage_two import verdict
from latentsindy._stage_two.fit.least_squares import HOPELESS, GiveUpWatch

pytestmark = pytest.mark.skipif(sys.platform != "linux" or len(os.sched_getaffinity(0)) < 2,
                                reason="the helper needs Linux and two cores")


@pytest.fixture(autouse=True)
def every_map_may_fork(monkeypatch):
    """A helper for every map, however short (the size rule is tested in
    tests/core/test_parallel.py): these tests are of the pieces shared."""
    monkeypatch.setattr(parallel, "FORK_WORTH", 0.0)


def prey_only():
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=1000, noise=0.01, seed=4)
    return discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3), t=data.t,
                           feature_names=["x"], verbose=False)


def test_a_discovery_is_the_same_with_the_second_process_and_without(monkeypatch):
    returned = []
    collect = parallel._collect

    def counted(*args):
        results = collect(*args)
        returned.append(len(results))
        return results

    monkeypatch.setattr(parallel, "_collect", counted)
    both = prey_only()
    # pieces were shared, and the helper's results came back (pickled and used)
    assert returned and sum(returned) > 0, returned
    previous = parallel.enable(False)
    try:
        alone = prey_only()
    finally:
        parallel.enable(previous)
    assert both.summary() == alone.summary()
    assert both.rhs == alone.rhs
    assert both.score == alone.score and both.score_se == alone.score_se
    assert np.array_equal(both.hidden, alone.hidden)
    assert [a.score for a in both.alternatives] == [a.score for a in alone.alternatives]
    assert both.doubts == alone.doubts


@dataclass(frozen=True)
class Scripted:
    """A stand-in proposal whose first fit is scripted: its data misfits (per degree of
    freedom) at the give-up checks, then its final misfit, or a blow-up at the end."""

    name: str
    checks: tuple
    final: float | None  # None: blows up after its checks
    seconds: float


def scripted_fit(p, ctx, options, best=np.inf, watch=None):
    """verdict.first_fit's give-up rule on a scripted proposal."""
    watch = GiveUpWatch() if watch is None else watch
    watch.dof = 1
    bound = best if callable(best) else (lambda: best)
    time.sleep(p.seconds)
    for cost in p.checks:
        if watch.check(cost, HOPELESS * max(bound(), 1.0)):
            return SimpleNamespace(proposal=p, fit=SimpleNamespace(residual_variance=cost))
    if p.final is None:
        return None
    return SimpleNamespace(proposal=p, fit=SimpleNamespace(residual_variance=p.final))


def test_first_fits_side_by_side_are_the_one_by_one_fits(monkeypatch, tmp_path):
    """Fits that start before a better one has finished (in the other process) run on
    under the looser bound; those the one-by-one order would have given up sooner are
    fitted again with its bound, so every fit is the loop's."""
    proposals = [
        Scripted("good, slow", (5.0, 2.0), 1.0, 1.0),
        Scripted("hopeless, would recover", (400.0, 300.0), 1.5, 0.05),  # given up at 400
        Scripted("hopeless", (80.0,), 60.0, 0.05),  # given up at 80
        Scripted("blows up late", (300.0,), None, 0.05),  # given up at 300 first
        Scripted("blows up early", (), None, 0.0),
        Scripted("fine", (3.0,), 1.2, 0.05),
    ]
    log = tmp_path / "calls"

    def logged(p, ctx, options, best=np.inf, watch=None):
        with open(log, "a") as fh:  # both processes append whole short lines
            fh.write(f"{os.getpid()}|{p.name}|{'again' if not callable(best) else ''}\n")
        return scripted_fit(p, ctx, options, best, watch)

    def calls():
        lines = log.read_text().splitlines() if log.exists() else []
        log.unlink(missing_ok=True)
        return [tuple(line.split("|")) for line in lines]

    monkeypatch.setattr(verdict, "first_fit", logged)
    options = SimpleNamespace(device="cpu")
    expected = [("good, slow", 1.0), ("hopeless, would recover", 400.0), ("hopeless", 80.0),
                ("blows up late", 300.0), ("fine", 1.2)]
    previous = parallel.enable(False)
    try:
        alone = verdict.first_fits(proposals, None, options)
    finally:
        parallel.enable(previous)
    assert [(t.proposal.name, t.fit.residual_variance) for t in alone] == expected
    assert len(calls()) == len(proposals)  # one by one: each fitted once, none again
    with single_thread():  # as in a discovery (the helper needs torch on one thread)
        both = verdict.first_fits(proposals, None, options)
    assert [(t.proposal.name, t.fit.residual_variance) for t in both] == expected
    named = {p.name: p for p in proposals}
    assert all(t.proposal is named[t.proposal.name] for t in both)  # the caller's own
    made = calls()
    assert len({pid for pid, _, _ in made}) == 2  # the helper fitted some
    # the helper started the hopeless one long before the good fit was known: with no
    # bound it recovered (1.5), so the parent fitted it again under the loop's bound
    assert (str(os.getpid()), "hopeless, would recover", "again") in made


def test_term_selection_refits_the_rest_side_by_side_only_after_the_first_fails(
        monkeypatch, tmp_path):
    """``terms._first_better`` makes its first exact refit alone; once that fails, the
    other attempts are made side by side, and the move chosen is the one-by-one loop's."""
    from latentsindy._stage_two.fit import terms

    log = tmp_path / "refits"

    def scripted_refit(problem, fit, model, keep, line):
        with open(log, "a") as fh:
            fh.write(f"{os.getpid()}|{keep}\n")
        time.sleep(0.2)
        return SimpleNamespace(bic=keep)  # the criterion after the move: keep's value

    monkeypatch.setattr(terms, "_refit", scripted_refit)
    monkeypatch.setattr(terms, "_bic", lambda trial, s2, price: trial.bic)
    problem = SimpleNamespace(options=SimpleNamespace(device="cpu"), joins=lambda t: True)

    def choose(criteria, base=5.0, gains=None, tabu=None):
        log.unlink(missing_ok=True)
        gains = gains or [10.0 - k for k in range(len(criteria))]
        moves = [(g, ("drop", (0, k)), c)
                 for k, (g, c) in enumerate(zip(gains, criteria, strict=True))]
        tabu = set() if tabu is None else tabu
        with single_thread():
            found = terms._first_better(problem, None, None, moves, base, 1.0, 1.0, tabu)
        made = [tuple(line.split("|")) for line in log.read_text().splitlines()]
        return found, made, tabu

    found, made, tabu = choose([3.0, 9.0, 1.0])  # the first refit succeeds: nothing more
    assert found[1] == ("drop", (0, 0)) and len(made) == 1 and not tabu
    found, made, tabu = choose([9.0, 4.0, 1.0])  # the second is the loop's choice
    assert found[1] == ("drop", (0, 1)) and tabu == {("drop", (0, 0))}
    assert len(made) == 3 and len({pid for pid, _ in made}) == 2  # the rest side by side
    found, made, tabu = choose([9.0, 8.0, 7.0])  # none lowers the criterion
    assert found is None and len(tabu) == 3
    # moves already refused are skipped, at most MAX_ATTEMPTS are refitted, and none
    # whose predicted gain is nil
    found, made, tabu = choose([9.0, 8.5, 8.0, 7.5, 1.0], tabu={("drop", (0, 1))})
    assert found is None and sorted(float(k) for _, k in made) == [7.5, 8.0, 9.0]
    assert len(tabu) == 4
    found, made, _ = choose([9.0, 1.0], gains=[10.0, 1e-9])
    assert found is None and [float(k) for _, k in made] == [9.0]
    previous = parallel.enable(False)
    try:  # without a second core the refits stop at the first that succeeds
        found, made, _ = choose([9.0, 4.0, 1.0])
    finally:
        parallel.enable(previous)
    assert found[1] == ("drop", (0, 1)) and len(made) == 2
