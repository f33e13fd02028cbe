"""Data stage one cannot read: a few samples per cycle, and panels of short recordings."""

from types import SimpleNamespace

import numpy as np
import pysindy as ps
import pytest
import sympy as sp

from latentsindy import discover_hidden, systems
from latentsindy._core import recordings

X, H = sp.symbols("x h", real=True)


def _assert_lotka_volterra_law(result, a, g, d, rel):
    """dx/dt = x h and the hidden law h' = a g - g h - a d x + d x h (h = a - b y), its
    four coefficients within ``rel``."""
    assert sp.expand(result.rhs["x"] - X * H) == 0
    law = sp.Poly(sp.expand(result.rhs["h"]), X, H).as_dict()
    truth = {(0, 0): a * g, (0, 1): -g, (1, 0): -a * d, (1, 1): d}
    assert set(law) == set(truth)
    for k, v in truth.items():
        assert float(law[k]) == pytest.approx(v, rel=rel)


def test_sixty_samples_over_eight_cycles_give_the_exact_law():
    """Prey-only Lotka-Volterra, 60 samples over 40 time units (about 8 per cycle), 1%
    noise: stage one keeps no term, and stage two, judging every carrier from
    integral-form hidden series, finds h = alpha - beta y with its exact law
    (h' = a g - g h - a d x + d x h: coefficients within 5%, measured 0.1-1.4%),
    confident: its law leaves terms out and the held-out check has power here (a right
    system's simulated score at most 3 noise variances); a note says that stage one did
    not help. The noise level is read from the best fit: the held-out score is near 1
    (0.5-2), not the 0.01 of the differences' 12-fold overestimate."""
    a, b, g, d = 1.0, 0.1, 1.5, 0.075
    data = systems.lotka_volterra(a, b, g, d, n_times=60, t_end=40.0, noise=0.01, seed=0)
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3), t=data.t,
                             feature_names=["x"], hidden_names=["h"], verbose=False)
    _assert_lotka_volterra_law(result, a, g, d, rel=0.05)
    assert 0.5 < result.score < 2.0
    assert result.doubts == () and result.confident
    assert any("so this law was found without it" in n for n in result.notes)
    reference = [n for n in result.notes if "a right system's held-out score" in n]
    assert len(reference) == 1
    assert float(reference[0].split(": ")[1].split()[0]) <= 3.0


def _panel(n_recordings, seed=0):
    """Prey counts of ``n_recordings`` subjects, 11 irregular samples each over about a
    cycle, cut from one run (1% noise)."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=4000, t_end=60.0)
    rng = np.random.default_rng(seed)
    x = data.x[:, :1] + 0.01 * data.x[:, 0].std() * rng.standard_normal((4000, 1))
    starts = rng.choice(4000 - 400, n_recordings, replace=False)
    rows = [s + np.sort(rng.choice(400, 11, replace=False)) for s in starts]
    return [x[r] for r in rows], [data.t[r] for r in rows]


def test_a_panel_of_short_recordings_is_pooled_and_held_out_by_recording():
    """20 recordings of 11 samples: none is long enough for stage one, together they
    hold 220; the law is searched by stage two alone over all of them (one law, each
    recording its own hidden start) and the result says so. The held-out check leaves
    whole recordings out, each fitted only in its initial values, so a right law's
    reference is about 1 (measured 1.08; held out by segments it was above 3 and the
    result was flagged `weak check`): the exact law (coefficients within 5%, measured
    0.1-1.3%), confident."""
    xs, ts = _panel(20)
    result = discover_hidden(xs, ps.PolynomialLibrary(degree=3), t=ts, feature_names=["x"],
                             hidden_names=["h"], verbose=False)
    assert result.data_use.segments == 20 and result.data_use.samples == 220
    assert any("so this law was found without it" in n for n in result.notes)
    _assert_lotka_volterra_law(result, 1.0, 1.5, 0.075, rel=0.05)
    reference = [n for n in result.notes if "a right system's held-out score" in n]
    assert len(reference) == 1
    assert 0.7 < float(reference[0].split(": ")[1].split()[0]) < 1.5
    assert result.doubts == () and result.confident


def test_panel_floor_is_about_information():
    """Pieces of 8-15 samples are used when no piece reaches 16 (a panel, or one short
    recording); pieces of 7 are refused with what would be enough."""
    xs, ts = _panel(6)
    segs, _, use = recordings.split(xs, ts)
    assert use.segments == 6 and [len(s) for s in segs] == [11] * 6
    segs, _, use = recordings.split(xs[:1], ts[:1])
    assert use.segments == 1 and use.samples == 11
    with pytest.raises(ValueError, match=r"at least 8 samples without a gap are needed in a "
                                         r"recording \(16 for stage one"):
        recordings.split([x[:7] for x in xs[:3]], [t[:7] for t in ts[:3]])


def test_one_short_recording_is_an_answer_flagged_not_a_refusal():
    """One recording of 11 samples: searched by stage two alone (a note says so); the
    law it finds there is not determined by 11 samples, and the result is flagged."""
    xs, ts = _panel(1)
    result = discover_hidden(xs, ps.PolynomialLibrary(degree=3), t=ts, feature_names=["x"],
                             verbose=False)
    assert result.data_use.segments == 1 and result.data_use.samples == 11
    assert any("no recording is long enough for stage one (16 samples between gaps)" in n
               for n in result.notes)
    assert not result.confident and result.doubts


def test_no_candidate_fitted_by_integration_is_an_unchecked_answer(monkeypatch):
    """When every candidate blows up or fails in the refinement (prey-only LV sampled 12
    or 16 times per cycle did so in 1 of 10 draws each), the result is the best-closing
    candidate, not checked and saying why and what to try, instead of an exception
    (0.2 raised; Van der Pol seen through x without a constant in the library at 5%
    noise: six candidates, all blew up)."""
    from latentsindy._stage_two import discover as module

    monkeypatch.setattr(module, "judge_all", lambda *args, **kw: ([], []))
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=400, t_end=20.0, noise=0.01)
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3), t=data.t,
                             feature_names=["x"], verbose=False)
    assert not result.confident and result.refinement is None
    assert [d.kind for d in result.doubts] == ["not checked"]
    assert "could be fitted by integration" in result.doubts[0]
    assert "include_bias=True" in result.doubts[0]


def test_every_carrier_that_fits_is_judged():
    """Without stage one, the integral-form closure score on 11-sample recordings ranks
    the carriers only roughly (prey-only LV panels: ``x^2`` above the exact ``x``, and
    its system then could not be integrated), so every carrier whose hidden series fits
    the data (within twice the best misfit) is proposed, not only the best-closing and
    the best-fitting one."""
    from latentsindy._core.library import fit_library
    from latentsindy._stage_two import context_build
    from latentsindy._stage_two.propose import hypotheses

    xs, ts = _panel(20)
    library = ps.PolynomialLibrary(degree=3)
    _, features = fit_library(library, xs, ["x"])
    support = np.zeros((1, len(features)), bool)
    ctx = context_build.bare(library, xs, ts, ["x"], features,
                             ps.PolynomialLibrary(degree=2), None, 0.05)
    carriers = hypotheses._usable([
        hypotheses.evaluate(hypotheses.single_term(1, len(features), 0, k, support), ctx,
                            "carrier") for k in range(len(features))])
    proposed = {p.structure.pivots for p in hypotheses.every_carrier(ctx, support)}
    assert len(carriers) >= 3
    assert {p.structure.pivots for p in carriers} <= proposed


def test_an_epidemic_wave_sampled_thirteen_times_gets_its_exact_law_confident():
    """One SIR wave (beta 0.6, gamma 0.2), only the infected observed, 13 samples, 1%
    noise: fewer segments than folds, so the check holds out interleaved samples (held
    out by segments, a right law's reference was 10-480 and the exact law was flagged
    `weak check`). The noise level read from neighbouring differences is several times
    too high at 13 samples; the selected law's misfit shows it and the judgement is
    redone in the lower level, so the exact law (h' = -beta I h - beta gamma I,
    coefficients within 10%) scores near 1 (0.5-3, measured 2.1) and is confident.
    Noise seeds 0-4 all gave the exact law, none a `weak check`; 3 of 5 confident, 2
    flagged `missing term` (a constant in dh/dt nearly called for on 13 samples)."""
    from scipy.integrate import solve_ivp

    beta, gamma = 0.6, 0.2
    t = np.linspace(0.0, 12.0 / (gamma * np.sqrt(beta / gamma - 1.0)), 13)
    sol = solve_ivp(lambda _, s: [-beta * s[0] * s[1], beta * s[0] * s[1] - gamma * s[1]],
                    (0.0, t[-1]), [0.995, 0.005], t_eval=t, rtol=1e-10, atol=1e-12)
    infected = sol.y[1]
    rng = np.random.default_rng(2)
    x = infected + 0.01 * infected.std() * rng.standard_normal(len(t))
    result = discover_hidden(x[:, None], ps.PolynomialLibrary(degree=2), t=t,
                             feature_names=["I"], hidden_names=["h"], verbose=False)
    i, h = sp.symbols("I h", real=True)
    assert sp.expand(result.rhs["I"] - i * h) == 0
    law = sp.Poly(sp.expand(result.rhs["h"]), i, h).as_dict()
    assert set(law) == {(1, 1), (1, 0)}
    assert float(law[(1, 1)]) == pytest.approx(-beta, rel=0.1)
    assert float(law[(1, 0)]) == pytest.approx(-beta * gamma, rel=0.1)
    assert 0.5 < result.score < 3.0
    assert result.doubts == () and result.confident


def test_a_carrier_whose_closure_starts_wrong_still_contends():
    """Prey-only Lotka-Volterra at 8 samples per cycle (40 samples, 1% noise): without
    stage one the exact carrier ``x`` starts from a wrong integral-form closure at 2.1
    times the best first fit (a saturated ``x^2`` law's), beyond the factor 2 that
    ends a hypothesis with stage one's closures; term selection mends its closure when
    it may contend (``judge.BLIND_CONTEND``), and the exact law wins, confident. The
    data are ``real_data.py``'s draw 1 at 8 per cycle, to full precision (rounded to 4
    digits, the old factor found the exact law too)."""
    a, b, g, d = 0.619472606246911, 0.13813955186501026, 1.2331952384602543, 0.022198829180679197
    data = systems.lotka_volterra(a, b, g, d, t_end=35.94370986619991, n_times=40,
                                  x0=(34.533413499401576, 5.357122748387013), noise=0.01,
                                  seed=1001)
    library = ps.PolynomialLibrary(degree=3, include_bias=False)
    result = discover_hidden(data.x[:, :1], library, t=data.t, feature_names=["x"],
                             hidden_names=["h"], verbose=False)
    _assert_lotka_volterra_law(result, a, g, d, rel=0.1)
    assert result.confident


def test_a_state_whose_noise_reads_low_does_not_buy_terms(monkeypatch):
    """The oscillator x' = A y, y' = B x with B logistic and hidden, 63 samples at 12 per
    cycle, 1% noise (``real_data.py``'s draw 2 there, to full precision): the data read
    x's noise at 0.69 of the truth and y's at 1.0, and the right law's residuals in x
    at 2.0 noise variances made ``x y`` in dx/dt pay. The judge puts the levels in
    the proportions of the best first fit's white residuals (``judge._balanced_noise``),
    and the observed equations are exact."""
    data = systems.harmonic_oscillator(
        A=-4.518920382116299, B=systems.Sigmoid(1.8960863805262678, 3.06678903447779,
                                                at=6.101919387285499,
                                                sharpness=1.3617123673767453),
        t_end=10.0, n_times=63, x0=(-0.8260953228373363, -0.563530405201243), noise=0.01,
        seed=1002)
    from latentsindy._stage_two import judge

    balanced = []
    original = judge._balanced_noise
    monkeypatch.setattr(judge, "_balanced_noise",
                        lambda trial: balanced.append(original(trial)) or balanced[-1])
    y = sp.Symbol("y", real=True)
    result = discover_hidden(data.x, ps.PolynomialLibrary(degree=2), t=data.t,
                             feature_names=["x", "y"], hidden_names=["h"], verbose=False)
    assert balanced and balanced[0] is not None  # the levels were balanced
    assert sp.Poly(result.rhs["x"], X, y).as_dict().keys() == {(0, 1)}
    assert sp.expand(result.rhs["y"] - H * X) == 0
    assert len(result.hidden_names) == 1


def _trial(residuals, sigma):
    """A judged trial's stand-in: one recording whose fitted path misses the data by
    ``residuals`` (in units of ``sigma``), with no fitted parameter."""
    from types import SimpleNamespace

    path = np.zeros((len(residuals), residuals.shape[1] + 1))
    observed = residuals * sigma + path[:, :-1]
    problem = SimpleNamespace(n_obs=residuals.shape[1], phi=np.zeros(residuals.shape[1]),
                              sigma=np.asarray(sigma, float), observed=[observed],
                              trajectories=lambda fit: [path])
    fit = SimpleNamespace(n_data=residuals.size, system=SimpleNamespace(n_free=0),
                          starts=np.zeros((0, 3)))
    return SimpleNamespace(problem=problem, fit=fit)


@pytest.mark.parametrize(("variances", "ratios"), [
    ((1.6, 0.9), (1.6 / 1.2, 0.9 / 1.2)),  # in proportion, the product kept
    ((3.0, 0.75), (1.5, 1 / 1.5)),  # each moved by at most IMBALANCE
    ((0.2, 1.0), (0.2, 1.0)),  # one read too high (below RESCALE): lowered to its fit
])
def test_noise_levels_are_balanced_on_white_residuals(variances, ratios):
    """White residuals at ``variances`` (noise variances of the data's estimate) give
    levels moved by the square roots of ``ratios`` (to 10%: 400 samples)."""
    from latentsindy._stage_two import judge

    rng = np.random.default_rng(0)
    white = rng.standard_normal((400, 2)) * np.sqrt(variances)
    sigma = np.array([0.1, 0.2])
    balanced = np.array(judge._balanced_noise(_trial(white, sigma)))
    assert balanced / sigma == pytest.approx(np.sqrt(ratios), rel=0.1)


def test_noise_levels_are_not_balanced_without_cause():
    """Residuals that follow a signal (a missing term), a lone observed state, AR(1)
    noise, residuals within ``IMBALANCE`` of each other, or a blown-up fit (NaN)
    change nothing."""
    from latentsindy._stage_two import judge

    rng = np.random.default_rng(0)
    white = rng.standard_normal((400, 2)) * np.sqrt([2.0, 0.8])
    sigma = np.array([0.1, 0.2])
    assert judge._balanced_noise(_trial(white, sigma)) is not None
    smooth = white.copy()
    smooth[:, 0] += 1.5 * np.sin(np.linspace(0, 6 * np.pi, 400))
    assert judge._balanced_noise(_trial(smooth, sigma)) is None
    assert judge._balanced_noise(_trial(white[:, :1], sigma[:1])) is None
    coloured = _trial(white, sigma)
    coloured.problem.phi = np.array([0.9, 0.9])
    assert judge._balanced_noise(coloured) is None
    assert judge._balanced_noise(_trial(rng.standard_normal((400, 2)), sigma)) is None
    blown = white.copy()
    blown[5, 1] = np.nan
    assert judge._balanced_noise(_trial(blown, sigma)) is None


# real_data.py's oscillator draws (to full precision): A, B's low and high levels, where
# it switches and how sharply, the start, and the span a recording is drawn from
_OSCILLATORS = {
    1: (-4.436237542874881, 2.2005055466785497, 1.697477655145755, 3.7416980347152813,
        0.8936487476598652, (0.9937046633844889, 0.11203143294593511), 435),
    4: (-3.318698599129487, 2.2069061274510027, 1.688550256076576, 4.153710063643107,
        1.4407485385951433, (0.859483867898534, 0.5111628711303036), 505),
}


def _oscillator_panel(draw=1):
    """The oscillator x' = A y, y' = B x with B logistic in time and hidden, seen as 20
    recordings of 11 irregular samples, each within about a cycle, 1% noise:
    ``real_data.py``'s 20 x 11 panel of the oscillator's ``draw``, sample for sample.
    Returns (recordings, times, (A, low, high, rate))."""
    a, low, high, at, rate, x0, span = _OSCILLATORS[draw]
    data = systems.harmonic_oscillator(
        A=a, B=systems.Sigmoid(low, high, at=at, sharpness=rate), t_end=10.0,
        n_times=2000, x0=x0)
    rng = np.random.default_rng([9, draw, 56])
    x = data.x + 0.01 * data.x.std(axis=0) * rng.standard_normal(data.x.shape)
    starts = np.sort(rng.choice(2000 - span - 1, 20, replace=False))
    rows = [s + np.sort(rng.choice(span, 11, replace=False)) for s in starts]
    return [x[r] for r in rows], [data.t[r] for r in rows], (a, low, high, rate)


def test_own_laws_give_the_other_equations_their_sparse_laws():
    """Without stage one, an equation with no term gets the sparse constant law its
    increments call for (forward selection on the integral form, extended BIC): on the
    oscillator's panel ``y`` in dx/dt (at most three terms, neither 1 nor x) and ``x`` in
    dy/dt; a row with terms and a fixed row are left as they are; pure noise
    calls for no term."""
    from latentsindy._stage_two.without_stage_one import _forward, own_laws

    xs, ts, _ = _oscillator_panel()
    library = ps.PolynomialLibrary(degree=2).fit(xs[0])
    ctx = SimpleNamespace(observed=xs, times=ts,
                          thetas=[np.asarray(library.transform(x)) for x in xs],
                          free_rows=np.array([True, True]))
    empty = np.zeros((2, 6), dtype=bool)
    laws = own_laws(ctx, empty)  # columns: 1 x y x^2 xy y^2
    # dx/dt = A y: y, and a curvature term or two for the trapezoid's error at 11
    # samples a cycle (term selection takes them out); dy/dt = B(t) x: x among the
    # terms of the approximation a law with constant coefficients makes of it
    assert laws[0, 2] and not laws[0, :2].any() and laws[0].sum() <= 3
    assert laws[1, 1]
    given = empty.copy()
    given[0, 3] = True
    assert own_laws(ctx, given)[0].tolist() == given[0].tolist()
    ctx.free_rows = np.array([True, False])
    assert not own_laws(ctx, empty)[1].any()
    rng = np.random.default_rng(0)
    assert not _forward(rng.standard_normal((220, 6)), rng.standard_normal(220), 10.0).any()


@pytest.mark.parametrize("draw", [1, 4])
def test_an_oscillator_panel_gets_its_exact_law(draw):
    """The oscillator's panel: the carrier of y' = B x needs x' = A y beside it, which no
    stage one gave (own laws, above), and the logistic law of B needs its constant and
    linear terms together (term selection adds two terms of one equation when no single
    move helps): the exact law, its coefficients within 10%, confident. Before, a wrong
    law (flagged); with the criterion's own laws alone, in draw 1 the right carrier with
    dB/dt = c B^2, confident (held-out 4.2 against a reference of 2.9), in draw 4 a
    wrong law (the right carrier's system beside A y, x^2 and y^2 could not be fitted:
    the sparsest own law is tried too)."""
    xs, ts, (a, lo, hi, r) = _oscillator_panel(draw)
    y = sp.Symbol("y", real=True)
    result = discover_hidden(xs, ps.PolynomialLibrary(degree=2), t=ts,
                             feature_names=["x", "y"], hidden_names=["h"], verbose=False)
    assert sp.Poly(result.rhs["x"], X, y).as_dict().keys() == {(0, 1)}
    assert float(sp.Poly(result.rhs["x"], X, y).as_dict()[(0, 1)]) == pytest.approx(
        a, rel=0.1)
    assert sp.expand(result.rhs["y"] - H * X) == 0
    _assert_logistic_law(result, lo, hi, r, rel=0.1)
    assert result.confident


def _assert_logistic_law(result, lo, hi, r, rel):
    """dh/dt = r (h - lo)(hi - h) / (hi - lo): a quadratic in h with these coefficients,
    each within ``rel``, and no other term."""
    truth = {(0,): -r * lo * hi / (hi - lo), (1,): r * (lo + hi) / (hi - lo),
             (2,): -r / (hi - lo)}
    law = sp.Poly(sp.expand(result.rhs["h"]), H).as_dict()
    assert set(law) == set(truth)
    for k, v in truth.items():
        assert float(law[k]) == pytest.approx(v, rel=rel)


def _short_oscillator_recordings():
    """``conditions.py``'s oscillator (B logistic in time, hidden) at 5% noise as four
    short recordings cut from one run, draw 2, sample for sample. Returns (recordings,
    times, (low, high, rate))."""
    a, low, high, at, rate = (-4.518920382116299, 1.8960863805262678, 3.06678903447779,
                              6.101919387285499, 1.3617123673767453)
    data = systems.harmonic_oscillator(
        A=a, B=systems.Sigmoid(low, high, at=at, sharpness=rate), t_end=10.0, n_times=2000,
        x0=(-0.8260953228373363, -0.563530405201243), noise=0.05, seed=1002)
    rng = np.random.default_rng([5, 2, 77])
    n_rec = int(rng.integers(3, 6))
    lengths, strides = rng.integers(200, 401, n_rec), rng.integers(1, 4, n_rec)
    while np.sum(lengths * strides) > 2000:
        strides[np.argmax(strides)] -= 1
    slack = 2000 - int(np.sum(lengths * strides))
    spaces = np.diff(np.sort(rng.integers(0, slack + 1, n_rec)), prepend=0)
    xs, ts, start = [], [], 0
    for length, stride, space in zip(lengths, strides, spaces, strict=True):
        rows = start + int(space) + stride * np.arange(length)
        xs.append(data.x[rows])
        ts.append(data.t[rows])
        start = int(rows[-1]) + 1
    return xs, ts, (low, high, rate)


def test_a_hidden_state_costs_an_initial_value_in_every_recording():
    """Four short recordings of the oscillator: B's rate as a second hidden state (one
    coefficient, ``dB/dt = r``, ``dr/dt = c r B``) fits as well as the logistic law (three)
    because each recording gets its own initial rate, a constant of its own. Counted
    once, the rate system was the smaller and won, and its first integral with one
    shared constant (``dB/dt = c B^2``) was reported, confident: wrong (held-out 1.15
    against 1.00). Counted once per recording, the second state's initial values make it
    the larger: the logistic law, confident."""
    xs, ts, (lo, hi, r) = _short_oscillator_recordings()
    assert [len(x) for x in xs] == [257, 391, 270, 347]
    result = discover_hidden(xs, ps.PolynomialLibrary(degree=2), t=ts,
                             feature_names=["x", "y"], hidden_names=["h"], verbose=False)
    assert result.hidden_names == ("h",) and sp.expand(result.rhs["y"] - H * X) == 0
    _assert_logistic_law(result, lo, hi, r, rel=0.15)
    assert result.confident
