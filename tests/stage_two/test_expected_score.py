"""The held-out score's reference: what a right system would score at this sampling,
and the checks that read the score against it."""

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pysindy as ps
import pytest
import sympy as sp
import torch
from test_refine import TRUTH_ROW, lv_problem, lv_system

from latentsindy import systems
from latentsindy._stage_two import without_stage_one as blind_path
from latentsindy._stage_two.doubts.checks import (
    FAR,
    REPRODUCTION_SLACK,
    reproduces,
    weak_check_doubts,
)
from latentsindy._stage_two.fit import expected_score as es
from latentsindy._stage_two.fit.expected_score import _noise, _with_data, expected_score
from latentsindy._stage_two.fit.held_out import (
    SHORT_RECORDING,
    by_recording,
    by_sample,
    cross_validate,
)
from latentsindy._stage_two.fit.refine import CONTINUOUS, Problem, RefineOptions

A, B, G, D = 1.0, 0.1, 1.5, 0.075


def _panel(n_recordings, noise=0.01, seed=0):
    """Prey of ``n_recordings`` subjects, 11 irregular samples each over about a cycle,
    with the true hidden state as the guess."""
    data = systems.lotka_volterra(A, B, G, D, n_times=4000, t_end=60.0)
    rng = np.random.default_rng(seed)
    x = data.x[:, :1] + noise * data.x[:, 0].std() * rng.standard_normal((4000, 1))
    h = A - B * data.x[:, 1]
    starts = rng.choice(4000 - 400, n_recordings, replace=False)
    rows = [s + np.sort(rng.choice(400, 11, replace=False)) for s in starts]
    return ([data.t[r] for r in rows], [x[r] for r in rows],
            [np.column_stack([data.x[r, 0], h[r]]) for r in rows])


def test_a_right_system_on_dense_data_is_expected_to_score_about_one():
    """1,500 samples in one recording: every held-out segment's start is pinned by its
    neighbours, so the reference is the noise alone (measured 0.98)."""
    data, guesses = lv_problem(0.01)
    problem = Problem(lv_system(TRUTH_ROW), [data.t], [data.x[:, :1]], guesses)
    assert expected_score(problem, problem.fit()) == pytest.approx(1.0, abs=0.25)


def test_segments_that_do_not_join_are_not_simulated():
    """A fit whose segments jump by several noise levels is no trajectory of its
    system: there is no right system's data to simulate, so there is no reference (its
    replicates' refits would trade the data for continuity and read far above 1)."""
    data, guesses = lv_problem(0.01)
    problem = Problem(lv_system(TRUTH_ROW), [data.t], [data.x[:, :1]], guesses)
    fit = problem.fit()
    assert fit.gap < 0.01 and fit.continuous
    starts = fit.starts.copy()
    starts[1::2, 0] += 5 * problem.sigma[0]  # every other segment moved by 5 noise levels
    broken = replace(fit, starts=starts, gap=problem._gap(fit.system, starts))
    assert broken.gap > CONTINUOUS and not broken.continuous
    assert expected_score(problem, broken) is None


def test_a_replicate_refitted_far_from_its_noise_leaves_no_reference(monkeypatch):
    """Each replicate's refit starts at the system that simulated it, so it ends within
    its noise's misfit (LM only lowers the cost; measured 0.99 of it here); a refit that
    ends more than ``REFITTED`` times above has lost that truth, and then there is no
    reference. Shown by lowering the bound below what a refit reaches."""
    data, guesses = lv_problem(0.01)
    problem = Problem(lv_system(TRUTH_ROW), [data.t], [data.x[:, :1]], guesses)
    fit = problem.fit()
    ratios = []

    def scored(synthetic, refit):  # each replicate's refit, as it is scored
        truth = synthetic.equations(fit.system, fit.starts, np.ones(synthetic.n_segments),
                                    fit.rho, jacobian=False).data_cost
        ratios.append(refit.data_cost / truth)
        return cross_validate(synthetic, refit)

    monkeypatch.setattr(es, "cross_validate", scored)
    assert expected_score(problem, fit) == pytest.approx(1.0, abs=0.25)
    assert len(ratios) == es.REPLICATES and max(ratios) <= 1.0 < es.REFITTED
    monkeypatch.setattr(es, "REFITTED", 0.5 * min(ratios))
    ratios.clear()
    assert expected_score(problem, fit) is None
    assert ratios == []  # the first replicate that misses decides: none is scored


def test_a_panel_is_held_out_by_recording_and_a_right_law_is_expected_near_one():
    """A panel of 12 recordings of 11 samples is held out recording by recording: each
    fold refits the law without its recordings, then only their initial values. A
    right law's misfit per degree of freedom is then the noise, so its reference is
    about 1 (held out by segments, each bridged from a neighbour of a few noisy
    samples, it was 5-20 and the check had no power); the right law meets it and a
    law without its x h term does not."""
    t, x, guesses = _panel(12)
    right = Problem(lv_system(TRUTH_ROW), t, x, guesses)
    assert by_recording(right)
    fit = right.fit()
    reference = expected_score(right, fit)
    score, se, errors = cross_validate(right, fit)
    assert len(errors) == 12  # one error per recording
    assert reference == pytest.approx(1.0, abs=0.3)
    assert reproduces(score, se, reference)
    wrong_row = TRUTH_ROW.copy()
    wrong_row[0] = 0.0  # without x h the law cannot follow the cycle
    wrong = Problem(lv_system(wrong_row), t, x, guesses)
    wrong_fit = wrong.fit()
    wrong_score, wrong_se, _ = cross_validate(wrong, wrong_fit)
    assert not reproduces(wrong_score, wrong_se, expected_score(wrong, wrong_fit))


def test_a_recording_held_out_is_fitted_only_in_its_initial_values():
    """The true law with every coefficient fixed, and one recording of the panel
    replaced by a steady rise over the prey's range (no orbit of the law rises for
    most of a cycle): started wherever that recording's samples put it best, the law
    cannot follow it, so its error alone is far above the others' (the noise)."""
    t, x, guesses = _panel(12)
    low, high = float(np.min(np.vstack(x))), float(np.max(np.vstack(x)))
    x[5] = np.linspace(low, high, len(t[5]))[:, None]
    fixed = lv_system(TRUTH_ROW, np.zeros(5, dtype=bool))
    problem = Problem(fixed, t, x, guesses)
    _, _, errors = cross_validate(problem, problem.fit())
    others = np.delete(errors, 5)
    assert np.all(others < 3.0) and errors[5] > 30 * np.median(others)


def test_only_panels_of_short_recordings_are_held_out_by_recording():
    """Whole recordings are the held-out units only where there are at least as many
    as folds and none is longer than SHORT_RECORDING segments: one long recording, or
    three short ones, keep segments bridged by their neighbours."""
    t, x, guesses = _panel(12)
    assert by_recording(Problem(lv_system(TRUTH_ROW), t, x, guesses))
    assert not by_recording(Problem(lv_system(TRUTH_ROW), t[:3], x[:3], guesses[:3]))
    data, long_guesses = lv_problem(0.01)
    one = Problem(lv_system(TRUTH_ROW), [data.t], [data.x[:, :1]], long_guesses)
    assert max(g.n_segments for g in one.groups) > SHORT_RECORDING
    assert not by_recording(one)


def _short(n_samples=13, noise=0.01, seed=0):
    """One prey recording of ``n_samples`` equally spaced samples over about a cycle
    and a half (the true hidden state as the guess)."""
    data = systems.lotka_volterra(A, B, G, D, n_times=n_samples, t_end=8.0)
    rng = np.random.default_rng(seed)
    x = data.x[:, :1] + noise * data.x[:, 0].std() * rng.standard_normal((n_samples, 1))
    return [data.t], [x], [np.column_stack([data.x[:, 0], A - B * data.x[:, 1]])]


def test_a_short_recording_is_held_out_by_samples_and_a_right_law_is_expected_near_one():
    """13 samples make fewer segments than the four folds: held out by segments,
    each fold would refit the law on half the samples or fewer and predict the rest
    (an exact epidemic law scored 20 noise variances there). Held out by interleaved
    samples, every held-out sample is bridged by integration from fitted samples on
    both sides: one error per sample, a right law's reference within [1, 2.5] (four
    coefficients and two initial values fitted to ten samples leave some error:
    measured 1.62), the right law reproduces (1.63 +- 0.80) and the law without x h
    does not (998)."""
    t, x, guesses = _short()
    known = RefineOptions(noise=(0.01 * x[0].std(),))  # the true level: plain scores
    right = Problem(lv_system(TRUTH_ROW), t, x, guesses, known)
    assert by_sample(right) and not by_recording(right)
    fit = right.fit()
    reference = expected_score(right, fit)
    score, se, errors = cross_validate(right, fit)
    assert len(errors) == 13
    assert 1.0 <= reference <= 2.5
    assert reproduces(score, se, reference)
    wrong_row = TRUTH_ROW.copy()
    wrong_row[0] = 0.0
    wrong = Problem(lv_system(wrong_row), t, x, guesses, known)
    wrong_fit = wrong.fit()
    wrong_score, wrong_se, _ = cross_validate(wrong, wrong_fit)
    assert not reproduces(wrong_score, wrong_se, expected_score(wrong, wrong_fit))


def test_a_sample_held_out_is_scored_where_it_lies():
    """The errors come in time order: a spike of 30 noise levels on sample 6 is the
    largest error, at index 6, several times the next (the folds that fit the spike
    have their starts pulled by it, so the others grow too)."""
    t, x, guesses = _short()
    sigma = 0.01 * x[0].std()
    x[0][6, 0] += 30 * sigma
    problem = Problem(lv_system(TRUTH_ROW, np.zeros(5, dtype=bool)), t, x, guesses,
                      RefineOptions(noise=(sigma,)))
    _, _, errors = cross_validate(problem, problem.fit())
    assert int(np.argmax(errors)) == 6
    assert errors[6] > 4 * np.max(np.delete(errors, 6))


def test_long_recordings_and_panels_are_not_held_out_by_samples():
    t, x, guesses = _panel(12)
    assert not by_sample(Problem(lv_system(TRUTH_ROW), t, x, guesses))
    data, long_guesses = lv_problem(0.01)
    assert not by_sample(Problem(lv_system(TRUTH_ROW), [data.t], [data.x[:, :1]],
                                 long_guesses))


def test_the_reference_is_the_same_for_the_same_data():
    t, x, guesses = _panel(6)
    problem = Problem(lv_system(TRUTH_ROW), t, x, guesses)
    fit = problem.fit()
    assert expected_score(problem, fit) == expected_score(problem, fit)


@pytest.mark.parametrize(("score", "se", "expected", "ok"), [
    (1.05, 0.1, 1.0, True),            # the noise: reproduced
    (2.0, 0.2, 1.0, False),            # significantly above
    (14.85, 5.3, 20.0, True),          # short recordings: a right law's reference is 20
    (673.0, 480.0, 4.14, False),       # too wide to be significant, yet far above
    (3.0, 2.0, 1.0, True),             # inconclusive and not far: no evidence against
])
def test_a_score_is_read_against_its_reference(score, se, expected, ok):
    assert reproduces(score, se, expected) is ok


def test_far_is_measured_from_the_slack_limit():
    """However wide the standard error, a score more than FAR times the limit (the
    reference with its slack) is no reproduction; just under it, it is."""
    limit = 1 + REPRODUCTION_SLACK
    assert not reproduces(1.01 * FAR * limit, 1e9, 1.0)
    assert reproduces(0.99 * FAR * limit, 1e9, 1.0)
    assert not reproduces(1.01 * FAR * 5 * limit, 1e9, 5.0)
    assert reproduces(0.99 * FAR * 5 * limit, 1e9, 5.0)


def _verdict(closure_row):
    """A judged prey-only LV law: x' = x h0, h0' = closure_row . (h0 x, 1, h0, x, h0^2,
    x^2), its closure library of degree 2 fitted on (h0, x)."""
    h0, x = sp.symbols("h0 x", real=True)
    library = ps.PolynomialLibrary(degree=2).fit(np.ones((3, 2)))
    features = (h0 * x, sp.Integer(1), h0, x, h0**2, x**2)
    coef = np.zeros((2, 6))
    coef[0, 0] = 1.0
    coef[1] = closure_row
    free = np.zeros((2, 6), dtype=bool)
    free[1] = np.asarray(closure_row) != 0
    system = SimpleNamespace(coef=coef, free=free, n_observed=1, state_names=("x", "h0"),
                             features=features)
    # as the closure fit keeps them: the library's output names, not the states'
    closure = SimpleNamespace(coef=np.zeros((1, 6)), library=library,
                              feature_names=tuple(library.get_feature_names(["h0", "x"])))
    return SimpleNamespace(system=system, proposal=SimpleNamespace(
        closure=closure, order=1, structure=SimpleNamespace(n_hidden=1)))


def test_a_law_found_without_stage_one_is_doubted_only_when_it_keeps_every_term():
    """Prey-only LV's exact law keeps 4 of the 6 terms of degree 2; a wrong carrier's
    approximation kept all 6 (at 8 samples per cycle and in a panel of 20 x 11)."""
    assert blind_path.saturated(_verdict([0.075, 1.5, -1.5, -0.075, 0.0, 0.0])) == []
    assert blind_path.saturated(_verdict([0.02, 0.03, -1.3, -8e-4, -58.0, 5e-6])) == [0]
    doubt = blind_path.doubt(True, ["h0"])
    assert doubt.kind == "without stage one"
    assert "dh0/dt keeps every term of the closure library" in doubt
    assert "16 samples between gaps" in doubt


def test_nothing_hidden_stands_alone_only_while_its_score_reproduces_the_data():
    """The law without hidden states, judged alone, stands at scores up to 1 +
    REPRODUCTION_SLACK, read as they stand (not within two standard errors); above, or
    unscored, or with nothing judged, the carriers are judged beside it."""
    def judged(cv, se=0.01, scored=True):
        return [SimpleNamespace(cv=cv, cv_se=se, scored=scored)]

    limit = 1.0 + blind_path.REPRODUCTION_SLACK
    assert blind_path.reproduced(judged(0.97))
    assert blind_path.reproduced(judged(limit))
    assert not blind_path.reproduced(judged(limit + 1e-9))
    assert not blind_path.reproduced(judged(1.45, se=0.46))  # 1.45 - 2 se would pass
    assert not blind_path.reproduced(judged(0.97, scored=False))
    assert not blind_path.reproduced([])


def test_simulated_noise_has_the_estimated_level_and_correlation():
    """White where no correlation was read; AR(1) with phi per median step, decaying
    as phi^(gap / step) across a longer gap."""
    t = np.arange(20000) * 0.1
    rng = np.random.default_rng(0)
    white = SimpleNamespace(n_obs=1, sigma=np.array([2.0]), phi=np.array([0.0]), times=[t])
    e = _noise(rng, t, white)[:, 0]
    assert e.std() == pytest.approx(2.0, rel=0.03)
    assert abs(np.corrcoef(e[:-1], e[1:])[0, 1]) < 0.03
    red = SimpleNamespace(n_obs=1, sigma=np.array([2.0]), phi=np.array([0.9]), times=[t])
    e = _noise(rng, t, red)[:, 0]
    assert e.std() == pytest.approx(2.0, rel=0.1)
    assert np.corrcoef(e[:-1], e[1:])[0, 1] == pytest.approx(0.9, abs=0.02)
    assert np.corrcoef(e[:-2:2], e[2::2])[0, 1] == pytest.approx(0.81, abs=0.03)


def test_the_reference_leaves_the_problem_it_was_simulated_from_unchanged():
    t, x, guesses = _panel(6)
    problem = Problem(lv_system(TRUTH_ROW), t, x, guesses)
    fit = problem.fit()
    before = [g.observed.clone() for g in problem.groups]
    expected_score(problem, fit)
    assert all(torch.equal(a, g.observed) for a, g in zip(before, problem.groups,
                                                         strict=True))
    assert all(np.array_equal(a, b) for a, b in zip(problem.observed, x, strict=True))
    same = _with_data(problem, problem.observed)
    assert all(torch.equal(a.observed, b.observed) for a, b in zip(same.groups,
                                                                   problem.groups,
                                                                   strict=True))


def test_a_check_on_few_recordings_is_weak_when_its_score_is_uncertain():
    """Held out by whole recordings, a score whose two standard errors exceed one noise
    variance could pass a law that misses every sample by a noise variance: indomethacin's
    six subjects (+-0.87) are flagged, panels of 10-20 recordings (+-0.03-0.26) are not;
    an unscored system and a segment-wise check are not judged this way."""
    (doubt,) = weak_check_doubts(1.05, "no recording is long enough", True, (6, 0.87))
    assert doubt.kind == "weak check"
    assert "6 leave its score uncertain by +-0.87 noise variances" in doubt
    assert weak_check_doubts(1.05, "no recording is long enough", True, (20, 0.26)) == ()
    assert weak_check_doubts(1.05, None, False, (6, 0.87)) == ()
    assert weak_check_doubts(1.05, None, True, None) == ()


def test_an_unmeasured_power_says_why():
    """A law found without stage one whose check's power is unknown is flagged, with
    the reason: its system could not be simulated, or max_time left the reference out."""
    (cannot,) = weak_check_doubts(None, "no law in the derivatives", True)
    assert "could not be simulated and refitted" in cannot
    (late,) = weak_check_doubts(None, "no law in the derivatives", True, None, True)
    assert "its power was not measured (max_time was spent first)" in late
    assert weak_check_doubts(None, None, True, None, True) == ()  # stage one helped


def test_a_score_doubt_whose_reference_max_time_left_out_says_so():
    """A score above ~1 is compared with 1 where the simulated reference is missing;
    where max_time left it out, the doubt says that a right system's score here was not
    simulated and may be higher (sparse samples: a right law can score several)."""
    from types import SimpleNamespace

    from latentsindy._stage_two.doubts.checks import doubts

    fit = SimpleNamespace(continuity_gap=0.0, status="converged", iterations=3)
    (plain,) = doubts(4.0, 0.1, fit, [], [])
    assert "expected ~1)" in plain
    (late,) = doubts(4.0, 0.1, fit, [], [], out_of_time=True)
    assert "expected ~1; a right system's score at this sampling was not simulated" in late
    (simulated,) = doubts(9.0, 0.1, fit, [], [], expected=2.0, out_of_time=True)
    assert "expected ~2 for a right system at this sampling, simulated" in simulated
    assert doubts(1.05, 0.1, fit, [], [], out_of_time=True) == ()
