"""A climb from a structure with many varying terms first sheds variations: its step
fits only the structures with one variation frozen, and the full step only where none
of them scores higher (``structure.DESCENT``)."""

from types import SimpleNamespace

import numpy as np
from test_side_by_side import oscillator  # xdot = a(t) y, ydot = -x

from latentsindy._core import parallel
from latentsindy._stage_one import structure
from latentsindy._stage_one.evidence import VaryingCoefficients
from latentsindy._stage_one.structure import DESCENT, StructureSearch


class Scripted(StructureSearch):
    """A search whose fits score as ``scores`` says (0 for any other structure), and
    which records every structure it is asked to fit."""

    def __init__(self, scores):
        self.scores, self.asked = scores, []
        self.free, self.allowed, self.pace, self.label = True, set(range(6)), {}, "test"
        self.model = SimpleNamespace(g=SimpleNamespace(n_features=5))

    def admissible(self, support, varying, adaptive, start=None):
        key = (frozenset(support), frozenset(varying))
        self.asked.append(key)
        return SimpleNamespace(score=self.scores.get(key, 0.0), support=tuple(sorted(support)),
                               varying=tuple(sorted(varying)), adaptive=adaptive)


def _key(support, varying):
    return frozenset(support), frozenset(varying)


def test_a_climb_sheds_variations_and_takes_the_full_step_where_none_helps(monkeypatch):
    """From five varying terms (above DESCENT = 3): no frozen variation scores higher,
    so the full step follows and takes the drop that does; at four varying terms the
    same again, and the climb ends there with the full step's neighbours."""
    monkeypatch.setattr(parallel, "_enabled", False)  # the neighbours in turn
    everything = set(range(5))
    start = _key(everything, everything)
    better = _key(everything - {4}, everything - {4})
    search = Scripted({start: 1000.0, better: 2000.0})
    fit = search.admissible(everything, everything, False)
    search.asked.clear()
    end, near = search.climb(fit, False)
    assert (set(end.support), set(end.varying)) == (everything - {4},) * 2
    freezes = [_key(everything, everything - {k}) for k in range(5)]
    full = search.neighbours(fit)
    assert search.asked[:5] == freezes  # the shedding step
    assert search.asked[5:5 + len(full)] == [_key(s, v) for s, v in full]
    four = everything - {4}
    rest = search.asked[5 + len(full):]
    assert rest[:4] == [_key(four, four - {k}) for k in range(4)]  # shedding again
    assert len(near) == len(rest) - 4 == len(search.neighbours(end))  # then the full step
    assert DESCENT == 3


def test_a_climb_that_sheds_asks_only_for_frozen_variations_while_they_help(monkeypatch):
    """Each freeze scores higher than the last: the climb descends from five varying
    terms to three by freezes alone (5 + 4 fits, not the 10 + 9 of full steps), then
    climbs as before."""
    monkeypatch.setattr(parallel, "_enabled", False)
    everything = set(range(5))
    scores = {_key(everything, everything): 1000.0,
              _key(everything, {0, 1, 2, 3}): 2000.0, _key(everything, {0, 1, 2}): 3000.0}
    search = Scripted(scores)
    fit = search.admissible(everything, everything, False)
    search.asked.clear()
    end, _ = search.climb(fit, False)
    assert set(end.varying) == {0, 1, 2}
    assert all(s == frozenset(everything) for s, _ in search.asked[:9])
    assert [len(v) for _, v in search.asked[:9]] == [4] * 5 + [3] * 4
    assert len(search.asked) == 9 + len(search.neighbours(end))


def test_shedding_ends_where_the_full_climb_does_on_a_real_model(monkeypatch):
    """The varying-coefficient model of xdot = a(t) y (library 1, x, y, x^2, y^2): from
    every term varying, the climb that sheds ends at the structure the full climb
    ends at, with fewer fits."""
    monkeypatch.setattr(parallel, "_enabled", False)
    t, x, theta = oscillator()
    scale = np.sqrt(np.mean(np.gradient(x, t, axis=0) ** 2, axis=0))
    ends = {}
    for descent in (DESCENT, 100):
        monkeypatch.setattr(structure, "DESCENT", descent)
        vc = VaryingCoefficients([x], [t], [theta], scale, 0.01 * x.std(axis=0))
        search = StructureSearch(vc.models[0], vc.basis, 0.05, True, set(range(5)),
                                 set(range(5)))
        everything = set(range(5))
        start = vc.models[0].fit(everything, everything)
        end, _ = search.climb(start, False)
        ends[descent] = (end.support, end.varying, len(vc.models[0]._cache))
    assert ends[DESCENT][:2] == ends[100][:2] == ((2,), (2,))  # a(t) y
    assert ends[DESCENT][2] < ends[100][2]
