"""max_time: a call returns the best system found by its deadline, saying what was not
judged; progress lines say which step runs and how many hypotheses remain."""

import numpy as np
import pysindy as ps
import pytest

from latentsindy import discover_hidden, systems
from latentsindy._core import budget, parallel


@pytest.fixture(scope="module")
def prey():
    return systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=400, t_end=20.0, noise=0.01)


def _discover(data, **options):
    return discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3), t=data.t,
                           feature_names=["x"], verbose=False, **options)


@pytest.mark.parametrize("bad, error", [(0, ValueError), (-1.0, ValueError),
                                        (float("nan"), ValueError), ("1 s", TypeError)])
def test_max_time_must_be_a_positive_number(prey, bad, error):
    with pytest.raises(error, match="max_time must be"):
        _discover(prey, max_time=bad)


def test_a_budget_spent_before_stage_two_gives_the_unchecked_best_candidate(prey):
    """Stage one always completes; with the budget spent by then, no hypothesis is
    fitted and the answer is the best-closing candidate, unchecked, with the budget's
    doubt naming what was left out."""
    result = _discover(prey, max_time=1e-6)
    assert not result.confident and result.refinement is None
    assert [d.kind for d in result.doubts] == ["not checked", "time budget"]
    assert "max_time was spent before any candidate" in result.doubts[0]
    left = result.doubts[1]
    assert "max_time=1e-06 s was spent" in left and "hypotheses not fitted" in left
    assert "Raise max_time" in left
    assert result.terms  # a system all the same


def test_a_budget_spent_after_the_first_fit_keeps_that_fit(prey, monkeypatch):
    """The deadline passes once the first hypothesis is fitted: the others are not
    started, nothing is scored, and the result is that refined system, flagged."""
    from latentsindy._stage_two import verdict

    monkeypatch.setattr(parallel, "_enabled", False)  # one process: one clock to stop
    fitted = verdict.first_fit

    def then_spent(*args, **kwargs):
        out = fitted(*args, **kwargs)
        budget._active.get().max_time = 0.0
        return out

    monkeypatch.setattr(verdict, "first_fit", then_spent)
    result = _discover(prey, max_time=1e6)
    assert result.refinement is not None and not result.confident
    kinds = [d.kind for d in result.doubts]
    assert "time budget" in kinds and "not scored" in kinds
    left = result.doubts[kinds.index("time budget")]
    assert "hypotheses not fitted" in left and "contending hypotheses not scored" in left
    assert "max_time was spent first" in result.doubts[kinds.index("not scored")]
    assert not np.isfinite(result.score)


def test_stage_one_structure_search_stops_where_it_is():
    """A budget spent before stage one's structure search: it keeps the structure it
    starts from and records that it stopped (the training itself always completes)."""
    from latentsindy import DynamicSINDy

    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=400, t_end=20.0, noise=0.01)
    with budget.budget(1e-9) as spent:
        DynamicSINDy(library=ps.PolynomialLibrary(degree=3), verbose=False).fit(
            data.x, data.t, feature_names=["x", "y"])
    assert spent.passed == ["stage one's structure search (stopped where it was)"]


def test_an_ample_budget_changes_nothing(prey):
    plain, budgeted = _discover(prey), _discover(prey, max_time=1e6)
    assert plain.confident and budgeted.confident
    assert str(plain.equations) == str(budgeted.equations)


def test_progress_lines_only_when_verbose(capsys):
    with budget.budget(None, verbose=False):
        budget.progress("quiet")
    assert "quiet" not in capsys.readouterr().err
    with budget.budget(None, verbose=True):
        budget.progress("first fit 1 of 3")
        assert not budget.expired()
    assert "] first fit 1 of 3" in capsys.readouterr().err
    with budget.budget(1e-9) as left:
        assert budget.spent("a step") and left.passed == ["a step"]
    budget.progress("outside")  # no budget: nothing printed, nothing expires
    budget.passed("anything")
    assert not budget.expired() and capsys.readouterr().err == ""
