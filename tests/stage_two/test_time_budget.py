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


@pytest.mark.parametrize("bad, error, says", [
    (0, ValueError, r"a number of seconds > 0 \(leave it out for no limit\); got 0"),
    (-1.0, ValueError, "a number of seconds > 0"),
    (float("nan"), ValueError, "a number of seconds > 0.*got nan"),
    (-float("inf"), ValueError, "a number of seconds > 0.*got -inf"),
    ("1 s", TypeError, r"a number; got '1 s' \(str\)"),
    ("15", TypeError, r"a number; got '15' \(str\)"),  # not read as 15 s
    (True, TypeError, r"a number; got True \(bool\)"),  # not one second
])
def test_max_time_must_be_a_positive_number(prey, bad, error, says):
    with pytest.raises(error, match="max_time must be " + says):
        _discover(prey, max_time=bad)


def test_an_infinite_max_time_is_no_limit():
    from latentsindy._core import validation

    assert validation.check_seconds(float("inf"), "max_time") is None
    assert validation.check_seconds(np.float32(2.5), "max_time") == 2.5
    assert validation.check_seconds(None, "max_time") is None


def test_a_budget_spent_before_stage_two_gives_the_unchecked_best_candidate(prey):
    """Stage one always completes; with the budget spent by then, no hypothesis is
    fitted and the answer is the candidate whose hidden states' equations best match
    stage one's series, unchecked, with the budget's doubt naming what was left out."""
    result = _discover(prey, max_time=1e-6)
    assert not result.confident and result.refinement is None
    assert [d.kind for d in result.doubts] == ["not checked", "time budget"]
    assert "max_time was spent before any candidate" in result.doubts[0]
    assert ("the candidate whose hidden states' equations best match stage one's "
            "estimated series, unchecked") in result.doubts[0]  # in words, not jargon
    left = result.doubts[1]
    assert "time budget (max_time=1e-06 s) did not allow" in left
    assert "hypotheses not fitted" in left
    assert "Raise max_time (--max-time on the command line)" in left
    assert "alternative proposals" in left and "adaptive slope priors" in left
    assert result.terms  # a system all the same


def test_a_spent_budget_leaves_the_alternative_proposals_out(prey, monkeypatch):
    """Stage one's own structure is always evaluated; the alternatives (other carriers,
    constants moved, reduced gauges, shared states) only while time is left."""
    from latentsindy._stage_two.propose import hypotheses

    origins = []
    evaluate, pruned = hypotheses.evaluate, hypotheses.pruned

    def recorded(structure, ctx, origin, *args):
        origins.append(origin)
        return evaluate(structure, ctx, origin, *args)

    def recorded_pruned(structure, ctx, origin):
        origins.append(origin)
        return pruned(structure, ctx, origin)

    monkeypatch.setattr(hypotheses, "evaluate", recorded)
    monkeypatch.setattr(hypotheses, "pruned", recorded_pruned)
    _discover(prey, max_time=1e-6)
    assert origins == ["stage one"]
    origins.clear()
    _discover(prey, refine=False)  # unbounded: the alternatives too
    assert origins[0] == "stage one" and "carrier" in origins and len(origins) > 10
    assert "carrier with every term, pruned" in origins


def test_a_budget_spent_after_the_first_fit_keeps_that_fit(prey, monkeypatch):
    """The deadline passes once the first hypothesis is fitted: the others are not
    started, nothing is scored, and the result is that refined system, flagged."""
    from latentsindy._stage_two import assemble, verdict

    monkeypatch.setattr(parallel, "_enabled", False)  # one process: one clock to stop
    fitted = verdict.first_fit

    def then_spent(*args, **kwargs):
        out = fitted(*args, **kwargs)
        budget._active.get().max_time = 0.0
        return out

    monkeypatch.setattr(verdict, "first_fit", then_spent)
    checked, checks = [], assemble._refitting_checks
    monkeypatch.setattr(assemble, "_refitting_checks",
                        lambda *args: checked.append(1) or checks(*args))
    result = _discover(prey, max_time=1e6)
    assert result.refinement is not None and not result.confident
    kinds = [d.kind for d in result.doubts]
    assert "time budget" in kinds and "not scored" in kinds
    left = result.doubts[kinds.index("time budget")]
    assert "hypotheses not fitted" in left and "contending hypotheses not scored" in left
    # the checks that refit the chosen system are left out, not run on refits cut short
    assert assemble.CHECKS in left and checked == []
    assert "max_time was spent first" in result.doubts[kinds.index("not scored")]
    assert not np.isfinite(result.score)


def test_stage_one_structure_search_stops_where_it_is():
    """A budget spent before stage one's structure search: it keeps the structure it
    starts from, with the Gaussian priors' fit (the adaptive priors' is not made), and
    records both (the training itself always completes)."""
    from latentsindy import DynamicSINDy

    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=400, t_end=20.0, noise=0.01)
    with budget.budget(1e-9) as spent:
        DynamicSINDy(library=ps.PolynomialLibrary(degree=3), verbose=False).fit(
            data.x, data.t, feature_names=["x", "y"])
    assert spent.passed == ["stage one's structure search (stopped where it was)",
                            "stage one's adaptive slope priors (Gaussian ones used)"]


def test_the_time_kept_for_closing_counts_to_the_end():
    """Time kept for what runs after the last check (the result) makes the budget count
    as spent that much early, to the end of the call; outside a budget nothing."""
    with budget.budget(10.0) as state:
        budget.keep_for_closing(1.0)
        assert not budget.expired() and state.closing == 1.0
        budget.keep_for_closing(11.0)
        assert budget.expired() and budget.spent("a step")
        assert state.passed == ["a step"]
        budget.keep_for_closing(0.5)  # a later, shorter training keeps the most asked
        assert state.closing == 11.0
    budget.keep_for_closing(11.0)  # outside a budget: nothing, and nothing carried over
    with budget.budget(10.0) as state:
        assert state.closing == 0.0 and not budget.expired()


def test_a_step_a_helper_left_out_is_seen_by_the_parent():
    """What a forked helper records is lost with it; what it left out is not, by name,
    here and in the text of the doubt, and after the budget's block has closed."""
    import os

    from latentsindy._stage_two.fit.expected_score import REFERENCE

    with budget.budget(10.0) as state:
        assert not state.elsewhere()
        budget.passed("a step here")  # the parent's own record is a list, as before
        assert not state.elsewhere()
        pid = os.fork()
        if pid == 0:  # the helper
            budget.passed("a step there")
            budget.passed(REFERENCE)
            budget.passed("a step there")  # once per kind of step
            os._exit(0)
        os.waitpid(pid, 0)
        assert state.elsewhere() and state.passed == ["a step here"]
        assert budget.left_out(REFERENCE) and not budget.left_out("another step")
        assert state.left_out() == f"a step here; a step there; {REFERENCE}"
    assert state.shared is None  # released, what it held kept
    assert state.left_out() == f"a step here; a step there; {REFERENCE}"
    with budget.budget(10.0) as state:
        assert state.left_out() is None  # nothing left out, the deadline ahead


def test_two_helpers_recording_at_once_lose_nothing():
    """An outer and an inner map's helpers can both write what they left out at the
    same moment (the budget runs out for both at once): each record is kept whole."""
    import os

    with budget.budget(10.0) as state:
        (ready_r, ready_w), (go_r, go_w) = os.pipe(), os.pipe()
        pids = []
        for who in ("outer", "inner"):
            pid = os.fork()
            if pid == 0:
                os.write(ready_w, b"r")
                os.read(go_r, 1)  # both start together
                for k in range(150):
                    budget.passed(f"{who} {k}")
                os._exit(0)
            pids.append(pid)
        for _ in pids:
            os.read(ready_r, 1)
        os.write(go_w, b"go")
        for pid in pids:
            os.waitpid(pid, 0)
        for fd in (ready_r, ready_w, go_r, go_w):
            os.close(fd)
        steps = state.elsewhere()
    assert sorted(steps) == sorted(f"{who} {k}" for who in ("outer", "inner")
                                   for k in range(150))


def test_a_full_record_says_that_more_was_left_out():
    with budget.budget(10.0) as state:
        for k in range(200):
            state.record_elsewhere(f"a step whose name is long, number {k:03d}")
        steps = state.elsewhere()
    assert steps[-1] == "more steps of the second process" and len(steps) < 200
    assert steps[:3] == [f"a step whose name is long, number {k:03d}" for k in range(3)]


@pytest.mark.parametrize("ending", ["in time", "helper cut", "past the deadline"])
def test_a_call_ending_in_the_time_kept_for_its_result(prey, monkeypatch, ending):
    """A call that left nothing out and ends within the time kept for its result is
    not flagged; one whose helper left a step out is, and the doubt names the step; one
    that left nothing out but ended past its deadline gets a note, not a doubt (its
    judgement is complete)."""
    from latentsindy._stage_two import discover

    finished = discover._discover

    def ends_late(*args, **kwargs):
        result = finished(*args, **kwargs)
        budget.keep_for_closing(1e9)  # from here on the budget counts as spent
        if ending == "helper cut":
            budget._active.get().record_elsewhere("a helper's step")
        if ending == "past the deadline":
            budget._active.get().start -= 2e6  # the deadline (1e6 s) is behind it
        return result

    monkeypatch.setattr(discover, "_discover", ends_late)
    result = _discover(prey, max_time=1e6)
    kinds = [d.kind for d in result.doubts]
    cut = ending == "helper cut"
    assert ("time budget" in kinds) == cut and result.confident != cut
    if cut:
        assert "left out: a helper's step." in result.doubts[-1]
    late = [n for n in result.notes if n.startswith("max_time=")]
    assert len(late) == (ending == "past the deadline")
    if late:
        assert "nothing was left out: the judgement is complete" in late[0]


@pytest.mark.parametrize("generator, steps", [
    ("timevae", {"support_steps": 40, "refit_steps": 80}),
    ("hypersindy", {"support_steps": 20, "refit_steps": 40, "min_epochs": 1, "window": 200})])
def test_stage_one_keeps_its_second_phase_time_for_closing(generator, steps):
    """Stage one's training (either generator) keeps the second phase's expected time
    (at the first phase's pace) to the end of the call, for what runs whatever the
    budget after it: the structure search between the phases keeps twice that, and
    stage two stops that much before the deadline."""
    from latentsindy import DynamicSINDy
    from latentsindy._stage_one import sequential, training

    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=400, t_end=20.0, noise=0.01)
    kept = []
    decide = training.between_phases

    def recorded(*args):
        state = budget._active.get()
        kept.append((state.reserve, state.closing))
        return decide(*args)

    with pytest.MonkeyPatch.context() as mp, budget.budget(1e6) as state:
        mp.setattr(training, "between_phases", recorded)
        mp.setattr(sequential, "between_phases", recorded)
        DynamicSINDy(library=ps.PolynomialLibrary(degree=3), verbose=False,
                     generator=generator, training=steps).fit(
            data.x, data.t, feature_names=["x", "y"])
        assert not budget.expired() and 0 < state.closing < state.elapsed()
        assert state.reserve == 0.0  # the phase's own reserve ends with it
        state.max_time = state.elapsed() + 0.5 * state.closing
        assert budget.expired()
    assert kept == [(state.closing, state.closing)]


def oscillator_model():
    """The varying-coefficient model of xdot = a(t) y, ydot = -x (a = 1 + 0.5 sin 0.2 t),
    library 1, x, y, x^2, y^2, and its search for dx/dt."""
    from latentsindy._stage_one.evidence import VaryingCoefficients
    from latentsindy._stage_one.structure import StructureSearch

    t = np.linspace(0, 40, 1500)
    a = 1.0 + 0.5 * np.sin(0.2 * t)
    phase = np.cumsum(np.sqrt(a)) * (t[1] - t[0])
    x = np.column_stack([np.sin(phase) * a ** 0.25, np.cos(phase) / a ** 0.25])
    x += 0.01 * x.std(axis=0) * np.random.default_rng(0).standard_normal(x.shape)
    theta = np.column_stack([np.ones(len(t)), x, x ** 2])
    scale = np.sqrt(np.mean(np.gradient(x, t, axis=0) ** 2, axis=0))
    vc = VaryingCoefficients([x], [t], [theta], scale, 0.01 * x.std(axis=0))
    return vc, StructureSearch(vc.models[0], vc.basis, 0.05, True, {0, 1, 2}, set(range(5)))


def test_a_climbing_step_the_budget_runs_out_in_is_not_taken(monkeypatch):
    """The budget runs out after the step's second neighbour: the third is not fitted,
    the climb ends where it stood, and the search records that it stopped."""
    from latentsindy._stage_one import structure

    monkeypatch.setattr(parallel, "_enabled", False)  # the neighbours in turn
    vc, search = oscillator_model()
    start = search.admissible({2}, {2}, False)
    asked = []
    fitted = search.admissible

    def counted(*args):
        asked.append(args[:2])
        if len(asked) == 2:
            budget._active.get().max_time = 0.0
        return fitted(*args)

    monkeypatch.setattr(search, "admissible", counted)
    with budget.budget(1e6) as spent:
        fit, near = search.climb(start, False)
    assert fit is start and near == []
    assert len(asked) == 2 < len(search.neighbours(start))
    assert spent.passed == [structure._STOPPED]


def test_a_slow_climbing_step_is_announced(monkeypatch, capsys):
    """With verbose, a climbing step expected to take a second or more says how many
    neighbours it fits and about how long; a quick one says nothing."""
    from latentsindy._stage_one import structure

    monkeypatch.setattr(parallel, "_enabled", False)
    monkeypatch.setattr(structure, "ANNOUNCE", 5.0)  # quick steps here take milliseconds
    _, search = oscillator_model()
    start = search.admissible({2}, {2}, False)
    with budget.budget(None, verbose=True):
        search.climb(start, False)  # no pace yet, then the quick steps' own: quiet
        assert "structure search" not in capsys.readouterr().err
        search.pace[False] = 1.0  # a second per neighbour, as on a spiking neuron
        search.climb(start, False)
    n = len(search.neighbours(start))
    assert n >= 5
    assert (f"] stage one's structure search, the equation, climbing step 1: {n} "
            f"neighbours to fit with Gaussian priors, about {n} s") in capsys.readouterr().err


def test_a_step_that_cannot_end_in_time_is_not_begun(monkeypatch):
    """Before its deadline, a climbing step whose neighbours at the last pace would end
    past it is not begun, and the search says it stopped; the adaptive priors left out
    for the time kept in reserve stay out of the posterior fitted after it."""
    from latentsindy._stage_one import structure

    monkeypatch.setattr(parallel, "_enabled", False)
    vc, search = oscillator_model()
    start = search.admissible({2}, {2}, False)
    search.pace[False] = 1e3  # a neighbour would take longer than the budget
    with budget.budget(1e2) as spent:
        assert search.climb(start, False) == (start, [])
        assert spent.passed == [structure._STOPPED] and not spent.expired()
        with budget.reserving(1e3):  # as stage one's second phase keeps its time
            choice = search.run([({2}, {2})])
        assert not spent.expired()
        fit = vc.fit(0, np.array([False, False, True, False, False]), np.ones(5, bool))
    assert not choice.fit.adaptive and not fit.adaptive
    assert fit is vc.models[0].fit([2], [2])  # the Gaussian fit the search made
    assert spent.passed == [structure._STOPPED, structure.GAUSSIAN]


def test_adaptive_priors_that_cannot_end_in_time_are_not_begun(monkeypatch):
    """The adaptive climb begins only where its first fit (up to EM_STEPS roughness
    searches, each about a Gaussian fit at the last pace) would end before the deadline;
    otherwise the Gaussian best stands, and the adaptive priors are recorded as left out."""
    from latentsindy._stage_one import structure

    monkeypatch.setattr(parallel, "_enabled", False)
    _, search = oscillator_model()
    best = search.admissible({2}, {2}, False)
    search.pace[False] = 30.0  # the climb may go on (30 s a neighbour), the fit may not
    with budget.budget(1e2) as spent:
        assert search._adaptive_climbs(best, [best]) == (best, [], None)
        assert spent.passed == [structure.GAUSSIAN] and not spent.expired()
    search.pace[False] = 1.0  # 5 s: it begins
    with budget.budget(1e2) as spent:
        fit, _, _ = search._adaptive_climbs(best, [best])
    assert fit.adaptive and spent.passed == []


def test_a_reduced_structure_neighbours_keep_its_priors(monkeypatch):
    """Where the budget left the adaptive priors out, the neighbours of a structure
    reduced by ``earned`` are fitted with its Gaussian priors too, so that rivals are
    scored on one footing (and fast)."""
    from latentsindy._stage_one import structure

    monkeypatch.setattr(parallel, "_enabled", False)
    _, search = oscillator_model()
    reduced = search.admissible({2}, set(), False)  # y constant: another structure
    asked, fitted = [], structure.in_turn

    def in_turn(s, step, adaptive, start):
        asked.append(adaptive)
        return fitted(s, step, adaptive, start)

    monkeypatch.setattr(structure, "in_turn", in_turn)
    monkeypatch.setattr(search, "climb", lambda fit, adaptive: (fit, []))
    monkeypatch.setattr(search, "earned", lambda fit, proposed: reduced)
    search.pace[False] = 30.0
    with budget.budget(1e2) as spent:
        choice = search.run([({2}, {2})])
    assert asked == [False] and choice.fit is reduced
    assert spent.passed == [structure.GAUSSIAN]
    assert not any(f.adaptive for f in choice.rivals)


def test_a_spent_budget_gives_the_exact_model_gaussian_priors():
    """With max_time spent, the posterior of a structure not yet fitted with adaptive
    slope priors is its Gaussian priors' fit (recorded as left out); one fitted already
    is used as it is."""
    vc, _ = oscillator_model()
    support, varying = np.array([False, False, True, False, False]), np.ones(5, bool)
    with budget.budget(1e-9) as spent:
        gaussian = vc.fit(0, support, varying)
    assert not gaussian.adaptive and gaussian.varying == (2,)
    assert spent.passed == ["stage one's adaptive slope priors (Gaussian ones used)"]
    adaptive = vc.fit(0, support, varying)  # no budget: adaptive priors
    assert adaptive.adaptive and adaptive.score != gaussian.score
    with budget.budget(1e-9) as spent:
        assert vc.fit(0, support, varying) is adaptive
    assert spent.passed == []


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
    assert capsys.readouterr().err == ""  # quiet: the budget's end not said either
    with budget.budget(1e-9, verbose=True):  # each step left out said once, as it is
        assert budget.spent("a step") and budget.spent("another") and budget.spent("a step")
    said = capsys.readouterr().err
    assert said.count("left out for the time budget (max_time=1e-09 s): ") == 2
    assert said.count(": a step\n") == 1 and said.count(": another\n") == 1
    budget.progress("outside")  # no budget: nothing printed, nothing expires
    budget.passed("anything")
    assert not budget.expired() and capsys.readouterr().err == ""
