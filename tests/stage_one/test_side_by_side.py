"""A structure search's climbing steps fitted by two processes: the same choice, the
same cached fits in the same order, whatever the helper does."""

import os
import sys
import time

import numpy as np
import pytest

from latentsindy._core import parallel
from latentsindy._stage_one import structure
from latentsindy._stage_one.evidence import VaryingCoefficients
from latentsindy._stage_one.structure import side_by_side

pytestmark = pytest.mark.skipif(sys.platform != "linux" or len(os.sched_getaffinity(0)) < 2,
                                reason="the helper needs Linux and two cores")


def oscillator(noise=0.01, n=1500):
    """xdot = a(t) y, ydot = -x, a(t) = 1 + 0.5 sin(0.2 t), as in test_vcm."""
    t = np.linspace(0, 40, n)
    a = 1.0 + 0.5 * np.sin(0.2 * t)
    phase = np.cumsum(np.sqrt(a)) * (t[1] - t[0])
    x = np.column_stack([np.sin(phase) * a ** 0.25, np.cos(phase) / a ** 0.25])
    x += noise * x.std(axis=0) * np.random.default_rng(0).standard_normal(x.shape)
    return t, x, np.column_stack([np.ones(n), x, x ** 2])  # 1, x, y, x^2, y^2


def test_every_step_side_by_side_gives_the_loops_search(monkeypatch):
    t, x, theta = oscillator()
    scale = np.sqrt(np.mean(np.gradient(x, t, axis=0) ** 2, axis=0))
    masks = (np.ones((2, 5), bool), np.ones((2, 5), bool), np.ones(2, bool),
             np.ones((2, 5), bool), 0.05)

    def search():
        vc = VaryingCoefficients([x], [t], [theta], scale, 0.01 * x.std(axis=0))
        return vc.choose(*masks), [m._cache for m in vc.models]

    used = []
    real = structure.side_by_side

    def counted(*args):
        fits, ran = real(*args)
        used.append(ran)
        return fits, ran

    monkeypatch.setattr(structure, "SIDE_BY_SIDE", 0.0)  # every step with two processes
    monkeypatch.setattr(structure, "side_by_side", counted)
    both, both_caches = search()
    assert used and set(used) == {2}
    previous = parallel.enable(False)
    try:
        alone, alone_caches = search()
    finally:
        parallel.enable(previous)
    for a, b in zip(both, alone, strict=True):
        assert (a.fit.support, a.fit.varying, a.fit.score, a.searched) == (
            b.fit.support, b.fit.varying, b.fit.score, b.searched)
        assert [(r.support, r.varying, r.score) for r in a.rivals] == [
            (r.support, r.varying, r.score) for r in b.rivals]
        assert [(r.support, r.varying, r.score) for r in a.apart] == [
            (r.support, r.varying, r.score) for r in b.apart]
        np.testing.assert_array_equal(a.fit.spline_cov, b.fit.spline_cov)
        np.testing.assert_array_equal(a.fit.edf, b.fit.edf)
    for a, b in zip(both_caches, alone_caches, strict=True):
        assert list(a) == list(b)  # the same structures, fitted in the same order
        for key in a:
            assert a[key].score == b[key].score
            np.testing.assert_array_equal(a[key].spline, b[key].spline)
            np.testing.assert_array_equal(a[key].log_rough, b[key].log_rough)


class Scripted:
    """A stand-in search: each neighbour asks for a chain of structures; a structure
    fitted is stamped with the neighbour that fitted it (a fit from another start)."""

    def __init__(self, chains):
        self.chains = chains
        self.model = self
        self._cache, self.looked = {}, None

    def admissible(self, name, _varying, _adaptive, _start):
        time.sleep(0.05)  # long enough for the helper to take neighbours too
        for key in self.chains[name]:
            if self.looked is not None:
                self.looked.append(key)
            if key not in self._cache:
                self._cache[key] = Stamp(key, name)
        return self._cache[self.chains[name][-1]]


class Stamp:
    def __init__(self, key, fitted_by):
        self.support, self.varying, self.adaptive = key
        self.fitted_by = fitted_by


def test_a_neighbour_that_needed_an_earlier_ones_fit_is_fitted_again():
    """Neighbour b's chain ends at the structure a fitted: the loop finds it cached
    (stamped a); side by side, b may have fitted it itself, and then it and every
    neighbour after it are fitted again in order."""
    chains = {name: [((j,), (), False) for j in chain] for name, chain in
              {"a": [1, 2], "b": [3, 2], "c": [4], "d": [5, 1]}.items()}
    step = [(name, None) for name in chains]
    for _ in range(3):  # which process takes which neighbour is a race
        assert_as_the_loop(Scripted(chains), chains, step)


def assert_as_the_loop(search, chains, step):
    """``side_by_side`` on ``search`` gives the loop's fits and cache, in its order."""
    loop = Scripted(chains)
    expected = [loop.admissible(n, None, False, None) for n, _ in step]
    fits, ran = side_by_side(search, step, False, None)
    assert ran == 2
    assert [(f.support, f.fitted_by) for f in fits] == [
        (f.support, f.fitted_by) for f in expected]
    assert list(search._cache) == list(loop._cache)
    assert [f.fitted_by for f in search._cache.values()] == [
        f.fitted_by for f in loop._cache.values()]


def test_only_the_neighbours_whose_lookups_changed_are_fitted_again(tmp_path):
    """One process takes b, c and d while the other's a runs; b fitted structure 2 that
    a fits in the loop, so b is fitted again here, but c and d asked only for their own
    structures: their fits are the loop's and are kept."""
    chains = {name: [((j,), (), False) for j in chain] for name, chain in
              {"a": [1, 2], "b": [3, 2], "c": [4], "d": [5]}.items()}
    step = [(name, None) for name in chains]
    calls = tmp_path / "calls"

    class Logged(Scripted):
        def admissible(self, name, *rest):
            with open(calls, "a") as fh:
                fh.write(f"{os.getpid()} {name}\n")
            if name == "a":
                time.sleep(0.5)  # the other process takes the others meanwhile
            return super().admissible(name, *rest)

    assert_as_the_loop(Logged(chains), chains, step)
    made = sorted(line.split()[1] for line in calls.read_text().splitlines())
    assert made == ["a", "b", "b", "c", "d"]  # b again, here; c and d not again


def test_a_step_the_budget_runs_out_in_is_not_taken(tmp_path):
    """max_time runs out while the neighbours are fitted (each takes 0.2 s, the budget
    0.3 s): the neighbours not begun by then are not fitted, the step gives no fits and
    the cache is as it was before it."""
    from latentsindy._core import budget

    chains = {name: [((j,), (), False)] for j, name in enumerate("abcde")}
    step = [(name, None) for name in chains]
    calls = tmp_path / "calls"

    class Slow(Scripted):
        def admissible(self, *args):
            with open(calls, "a") as fh:
                fh.write(f"{args[0]}\n")
            time.sleep(0.15)
            return super().admissible(*args)

    search = Slow(chains)
    search._cache = {"before": Stamp(((9,), (), False), "start")}
    with budget.budget(0.3) as spent:
        fits, ran = side_by_side(search, step, False, None)
    assert fits is None and ran == 2
    assert len(calls.read_text().split()) < len(step)  # the last one not begun
    assert list(search._cache) == ["before"]
    assert spent.passed == []  # the climb records what was left out, not the step


def test_the_steps_outside_the_climbs_side_by_side_are_the_loops(monkeypatch):
    """The rival optima's adaptive fits and the neighbours of a structure reduced by
    ``earned`` go side by side too (``fit_structures``), with the loop's fits (new
    ones: each search starts afresh) and cache."""
    from latentsindy._stage_one.structure import StructureSearch

    t, x, theta = oscillator()
    scale = np.sqrt(np.mean(np.gradient(x, t, axis=0) ** 2, axis=0))
    steps = []
    real = structure.fit_structures

    def counted(search, step, *rest):
        new = sum(not search.model.fitted(s, v, rest[0]) for s, v in step)
        fits, ran = real(search, step, *rest)
        steps.append((sys._getframe(1).f_code.co_name, len(step), new, ran,
                      [(f.support, f.varying, f.adaptive, f.score, tuple(f.log_rough))
                       for f in fits]))
        return fits, ran

    def fresh():
        vc = VaryingCoefficients([x], [t], [theta], scale, 0.01 * x.std(axis=0))
        return StructureSearch(vc.models[0], vc.basis, 0.05, True, {0, 1, 2}, set(range(5)))

    def searches():
        s = fresh()
        found = [s.admissible(*start, False) for start in (  # four Gaussian optima
            [{0, 2}, {0}], [{2}, {2}], [{2}, set()], [{2, 3}, {3}])]
        s._adaptive_climbs(max(found, key=structure.penalised), found)
        s = fresh()  # the reduced structure's neighbours not fitted yet
        reduced = s.admissible({0, 2}, {0}, True)
        monkeypatch.setattr(s, "climb", lambda fit, adaptive: (fit, []))
        monkeypatch.setattr(s, "earned", lambda fit, proposed: reduced)
        s.pace[True] = 1.0
        choice = s.run([({2}, {2})])
        return choice, s.model._cache, len(s.neighbours(reduced))

    monkeypatch.setattr(structure, "SIDE_BY_SIDE", 0.0)
    monkeypatch.setattr(structure, "fit_structures", counted)
    choice, cache, n_near = searches()
    both = [step for step in steps if step[0] != "climb"]
    assert [step[:4] for step in both] == [
        ("_adaptive_climbs", 3, 2, 2),  # the Gaussian best's three rivals, two new
        ("run", n_near, n_near, 2)]  # the reduced structure's neighbours, all new
    # with the reduced structure's adaptive priors (where something varies)
    assert all(adaptive for _, varying, adaptive, *_ in both[1][4] if varying)
    steps.clear()
    previous = parallel.enable(False)
    try:
        alone_choice, alone_cache, _ = searches()
    finally:
        parallel.enable(previous)
    alone = [step for step in steps if step[0] != "climb"]
    assert [step[3] for step in alone] == [1, 1]
    assert [step[4] for step in both] == [step[4] for step in alone]  # the same fits
    assert [(r.support, r.varying, r.score) for r in choice.rivals] == [
        (r.support, r.varying, r.score) for r in alone_choice.rivals]
    assert list(cache) == list(alone_cache)
    assert [f.score for f in cache.values()] == [f.score for f in alone_cache.values()]
