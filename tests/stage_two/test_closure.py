"""Stage two's building blocks against analytic truth: the closure (first order and a
rate's second-order weak form) and the structured hidden-series smoother."""

from dataclasses import make_dataclass
from types import SimpleNamespace

import numpy as np
import pysindy as ps
import pytest
import scipy.sparse as sps
import sympy as sp
from scipy.integrate import solve_ivp

from latentsindy import systems
from latentsindy._stage_two.propose.closure import (
    ClosureFit,
    fit_closure,
    fit_rate_closure,
    path,
    support_error,
    with_levels,
)
from latentsindy._stage_two.propose.hypotheses import fuller_closure, gauge_free_support
from latentsindy._stage_two.propose.shared import carrier_pairs
from latentsindy._stage_two.propose.smoother import (
    Structure,
    _sparse_solve,
    fit_hidden,
    prune_constants,
    single_term,
)


def test_closure_integral_refit_is_exact_on_clean_data():
    """The closure's final fit (increments over ``span`` samples against the library's
    integrals) is exact on exact data: the predator's equation of noise-free
    Lotka-Volterra within 1e-4, pointwise-like (span 1) or over 45 samples."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    y, x = data.x_clean[:, 1:2], data.x_clean[:, :1]
    ydot = data.x_dot[:, 1:2]
    for span in (1, 45):
        fit = fit_closure([y], [ydot], [x], [data.t], ps.PolynomialLibrary(degree=2),
                          ["y"], ["x"], span=span)
        found = dict(zip(fit.feature_names, fit.coef[0], strict=True))
        assert {k for k, v in found.items() if v != 0} == {"y", "y x"}
        assert found["y"] == pytest.approx(-1.5, rel=1e-4)
        assert found["y x"] == pytest.approx(0.075, rel=1e-4)
        # the exact support is also the least-error one; the richer support offered to
        # the judge adds only the constant (y's own level), which exact data refit to 0
        richer = dict(zip(fit.feature_names, fit.fuller[0], strict=True))
        assert {k for k, v in richer.items() if v != 0} == {"1", "y", "y x"}
        assert richer["1"] == pytest.approx(0.0, abs=1e-3)
        assert richer["y"] == pytest.approx(-1.5, rel=1e-3)


def test_closure_keeps_its_least_error_support_beside_the_sparser_choice():
    """With noisy rates the one-standard-error rule often picks a sparser support than
    the one of least held-out error: that one is kept (``fuller``, refitted, with its
    error) for the judge to try; when the rule picked it, there is none (a library
    without a constant: no level to add, see the next test)."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    y, x = data.x_clean[:, 1:2], data.x_clean[:, :1]
    ydot = data.x_dot[:, 1:2]
    offered = 0
    for seed in range(6):
        noisy = ydot + np.std(ydot) * np.random.default_rng(seed).standard_normal(ydot.shape)
        fit = fit_closure([y], [noisy], [x], [data.t], ps.PolynomialLibrary(
            degree=2, include_bias=False), ["y"], ["x"])
        errors = [e for _, _, e in fit.table]
        if fit.fuller is None:
            assert fit.cv_error == min(errors)
            continue
        offered += 1
        assert np.count_nonzero(fit.fuller) > np.count_nonzero(fit.coef)
        assert fit.fuller_error == min(errors) < fit.cv_error
    assert offered >= 2


def test_the_richer_support_carries_a_hidden_states_level():
    """Chen's system with z hidden: h = c - a - z obeys dh/dt = -b h - x y + b (c - a).
    h varies little about a mean far from zero, so its column and the constant are
    nearly one: with rates from a noisy h the one-standard-error rule drops the
    constant (b (c - a) = -19), and the law without it has the wrong level. The richer
    support offered to the judge carries it, refitted close to the truth; its held-out
    error is that support's own (``support_error``). With the constant chosen, no own
    linear term, or a state whose mean is below its spread, nothing is added
    (``with_levels``)."""
    a, b, c = 35.0, 2.92, 28.5
    t = np.linspace(0.0, 10.0, 2001)
    sol = solve_ivp(lambda _, s: [a * (s[1] - s[0]), (c - a) * s[0] - s[0] * s[2] + c * s[1],
                                  s[0] * s[1] - b * s[2]],
                    (0, 10), [-3.0, 2.0, 20.0], t_eval=t, rtol=1e-10, atol=1e-10)
    xy, h = sol.y[:2].T, (c - a) - sol.y[2:].T
    rng = np.random.default_rng(0)
    noisy = h + 0.02 * np.std(h) * rng.standard_normal(h.shape)
    rates = np.gradient(noisy[:, 0], t)[:, None]
    for span in (1, 20):
        fit = fit_closure([noisy], [rates], [xy], [t], ps.PolynomialLibrary(degree=2),
                          ["h"], ["x", "y"], span=span)
        chosen = dict(zip(fit.feature_names, fit.coef[0], strict=True))
        richer = dict(zip(fit.feature_names, fit.fuller[0], strict=True))
        assert chosen["h"] != 0 and chosen["1"] == 0
        assert richer["1"] == pytest.approx(b * (c - a), rel=0.1)
        assert richer["h"] == pytest.approx(-b, rel=0.1)
        assert richer["x y"] == pytest.approx(-1.0, rel=0.05)
        theta = np.asarray(fit.library.transform(np.hstack([noisy, xy])))
        assert fit.fuller_error == support_error(theta, rates, fit.fuller != 0)
        assert fit.fuller_error != fit.cv_error
    far = np.column_stack([5.0 + np.sin(t), 5.0 + np.cos(t)])  # means above spreads
    names = ("1", "h", "x", "h x")
    keep = np.array([[False, True, True, False], [True, True, False, False]])
    assert with_levels(keep, names, ("h", "g"), [far]).tolist() == [
        [True, True, True, False], [True, True, False, False]]
    assert with_levels(keep[1:], names, ("h",), [far[:, :1]]) is None  # its constant is there
    # a state that swings about zero (mean below its spread) gets none: there its
    # column and the constant are far from one, and held-out rates judge the constant
    both = np.array([[False, True, False, True], [False, False, True, True]])
    pair = ("1", "h", "g", "h g")
    assert with_levels(both, pair, ("h", "g"), [far]).tolist() == [
        [True, True, False, True], [True, False, True, True]]
    swings = [np.column_stack([np.sin(t), 5.0 + np.sin(t)])]  # h about 0, g about 5
    assert with_levels(both, pair, ("h", "g"), swings).tolist() == [
        [False, True, False, True], [True, False, True, True]]
    assert with_levels(both, pair, ("h", "g"), [np.column_stack([np.sin(t), np.cos(t)])]) \
        is None
    own_absent = np.array([[True, False, True, False]])  # h, h x: no x, no constant
    assert with_levels(own_absent, ("h", "x", "h x", "1"), ("x",), [far[:, :1]]) is None
    assert with_levels(keep[:1, 1:], names[1:], ("h",), [far[:, :1]]) is None  # no constant


def test_stlsq_path_contains_the_sparse_truth():
    """Exact sparse linear data: the path holds the true support with zero held-out
    error, and every denser support is no better."""
    rng = np.random.default_rng(0)
    theta = rng.standard_normal((500, 6))
    target = (theta @ np.array([0.0, 2.0, 0.0, -0.5, 0.0, 0.0]))[:, None]
    candidates = path(theta, target)
    true = [c for c in candidates if list(np.flatnonzero(c[4][0])) == [1, 3]]
    assert len(true) == 1 and true[0][2] < 1e-12
    np.testing.assert_allclose(true[0][4][0, [1, 3]], [2.0, -0.5], rtol=1e-8)


def test_rate_closure_recovers_a_second_order_law():
    """B(t) = b0 + a sin(w t + p) obeys B'' = -w^2 (B - b0): the second-order weak form
    finds exactly the terms 1 and B of the rate's equation within 0.1%, from B alone
    (its rate from a smooth derivative)."""
    t = np.linspace(0, 30, 2000)
    w, b0 = 0.6, 2.5
    b = (b0 + 0.5 * np.sin(w * t + 0.3))[:, None]
    rate = (0.5 * w * np.cos(w * t + 0.3))[:, None]
    x = np.cos(3 * t)[:, None]  # an unrelated observed state
    fit = fit_rate_closure([b], [rate], [x], [t], ps.PolynomialLibrary(degree=2),
                           ["g", "B", "x"], span=20)
    found = {n: c for n, c in zip(fit.feature_names, fit.coef[0], strict=True) if c != 0}
    assert set(found) == {"1", "B"}
    assert found["B"] == pytest.approx(-w**2, rel=1e-3)
    assert found["1"] == pytest.approx(w**2 * b0, rel=1e-3)


def _sigma(x):
    return np.full(x.shape[1], 1e-3) * x.std(axis=0)


@pytest.mark.parametrize("missing_diagonal", [False, True])
def test_the_smoothers_scaled_solve_is_the_products_formulation(missing_diagonal):
    """The smoother's solve scales the stored entries in place: the same numbers, bit
    for bit, as ``diags(d) @ M @ diags(d) + 1e-10 I`` built as sparse products (with a
    column of zeros, whose diagonal entry is not stored, too), and the solution of the
    ridged system."""
    from scipy.sparse.linalg import spsolve

    rng = np.random.default_rng(0)
    n = 60
    a = sps.random(3 * n, n, density=0.1, random_state=1, format="csc")
    a = a @ sps.diags(rng.uniform(0.1, 100.0, n))  # columns of very different sizes
    if missing_diagonal:
        a = a @ sps.diags(np.r_[np.ones(n - 1), 0.0])
    matrix = (a.T @ a).tocsc()
    matrix.eliminate_zeros()
    rhs = rng.normal(size=n)
    if missing_diagonal:
        rhs[-1] = 0.0  # the empty column's equation: 1e-10 x = 0
    d = 1.0 / np.sqrt(np.maximum(matrix.diagonal(), 1e-300))
    products = sps.diags(d) @ matrix @ sps.diags(d) + 1e-10 * sps.identity(n, format="csc")
    expected = d * spsolve(products.tocsc(), d * rhs)
    np.testing.assert_array_equal(_sparse_solve(matrix, rhs), expected)
    dense = products.toarray()
    np.testing.assert_allclose(dense @ (expected / d), d * rhs, rtol=1e-8, atol=1e-8)


def test_smoother_recovers_a_varying_coefficient():
    """Prey-only Lotka-Volterra without noise: the structure xdot = h x gives h = alpha -
    beta y with R^2 > 0.9999."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    x = data.x_clean[:, :1]
    support = np.zeros((1, 1), dtype=bool)
    fit = fit_hidden(single_term(1, 1, 0, 0, support), [x], [x], [data.t], _sigma(x), 2)
    truth = 1.0 - 0.1 * data.x_clean[:, 1]
    resid = fit.hidden[0][:, 0] - truth
    assert 1 - resid.var() / truth.var() > 0.9999
    assert abs(resid.mean()) < 1e-3


def test_smoother_recovers_a_shared_hidden_state():
    """The modulated oscillator: z enters xdot through x (coefficient z) and ydot through
    y (coefficient k z). With loadings started 30% off, the smoother returns k within
    2% and one hidden series for both."""
    k = 1.3
    data = systems.modulated_oscillator(omega=1.5, k=k, epsilon=1.0, n_times=2000)
    xy = data.x_clean[:, :2]
    theta = xy  # library [x, y]
    support = np.ones((2, 2), dtype=bool)
    loads = np.zeros((2, 2, 1))
    loads[0, 0, 0], loads[1, 1, 0] = 1.0, 0.7 * k
    fit = fit_hidden(Structure(support, loads, ((0, 0),)), [theta], [xy], [data.t],
                     _sigma(xy), 2, iterations=8)
    assert fit.structure.loadings[1, 1, 0] == pytest.approx(k, rel=0.02)
    truth = data.x_clean[:, 2]
    resid = fit.hidden[0][:, 0] - truth
    assert 1 - resid.var() / truth.var() > 0.999


def test_pruning_keeps_real_terms_and_drops_absent_ones():
    """FitzHugh-Nagumo with the constant term as the carrier of the hidden input: from
    every cubic term as a constant, pruning keeps v and v^3 (coefficients within 5%)
    and drops v^2 (measured 2.6%: the smoother splits the fast part of the rate
    between h and the constants only as well as its prior allows; refinement polishes)."""
    data = systems.fitzhugh_nagumo(n_times=2000)
    v = data.x_clean[:, :1]
    lib = ps.PolynomialLibrary(degree=3).fit(v)
    theta = lib.transform(v)  # 1, v, v^2, v^3
    support = np.ones((1, 4), dtype=bool)
    fit = fit_hidden(single_term(1, 4, 0, 0, support), [theta], [v], [data.t], _sigma(v), 2)
    fit = prune_constants(fit, [theta], [v], [data.t], _sigma(v), 2, 0.05,
                          np.ones(1, dtype=bool))
    assert fit.structure.support.tolist() == [[True, True, False, True]]
    assert fit.constants[0, 1] == pytest.approx(1.0, rel=0.05)
    assert fit.constants[0, 3] == pytest.approx(-1.0 / 3.0, rel=0.05)


def test_closure_leaves_extrapolated_ends_out_of_the_selection():
    """Lotka-Volterra's predator law from three pieces whose rates are badly wrong in the
    first and last 30 samples (as a differentiator's extrapolated ends can be): with
    those ends named, the true terms y and y x are found within 0.1%; without, the wrong
    rates decide the support."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=3000)
    pieces = [slice(0, 1000), slice(1000, 2000), slice(2000, 3000)]
    y = [data.x_clean[p, 1:2] for p in pieces]
    x = [data.x_clean[p, :1] for p in pieces]
    t = [data.t[p] for p in pieces]
    ydot = [data.x_dot[p, 1:2].copy() for p in pieces]
    for d in ydot:
        d[:30] += 5.0 * np.abs(d).max()
        d[-30:] -= 5.0 * np.abs(d).max()

    def support(fit):
        return {n for n, c in zip(fit.feature_names, fit.coef[0], strict=True) if c != 0}

    args = (y, ydot, x, t, ps.PolynomialLibrary(degree=2), ["y"], ["x"])
    fit = fit_closure(*args, span=45, edges=[30, 30, 30])
    assert support(fit) == {"y", "y x"}
    found = dict(zip(fit.feature_names, fit.coef[0], strict=True))
    assert found["y"] == pytest.approx(-1.5, rel=1e-3)
    assert found["y x"] == pytest.approx(0.075, rel=1e-3)
    assert support(fit_closure(*args, span=45)) != {"y", "y x"}


def test_gauge_free_support_drops_what_the_hidden_state_can_carry():
    """Carrier x in dx/dt with stage one's constants 1, x^2, x^3 and y: x^2 and x^3 are
    x times monomials (a hidden h absorbs them), 1 and y are not, and another equation's
    terms stay; a hidden state seen through two terms keeps its equation whole."""
    x, y = sp.symbols("x y", real=True)
    exprs = (sp.Integer(1), x, y, x**2, x**3)
    support = np.array([[True, True, True, True, True], [False, True, False, True, False]])
    loads = np.zeros((2, 5, 1))
    loads[0, 1, 0] = 1.0
    st = Structure(support, loads, ((0, 1),))
    free = np.array([True, True])
    kept = gauge_free_support(st, exprs, free)
    assert kept[0].tolist() == [True, True, True, False, False]
    np.testing.assert_array_equal(kept[1], support[1])
    assert np.array_equal(gauge_free_support(st, exprs, np.array([False, True])), support)
    loads[1, 1, 0] = 0.5  # the same hidden state also in dy/dt
    assert np.array_equal(gauge_free_support(Structure(support, loads, ((0, 1),)), exprs,
                                             free), support)


def test_a_proposal_with_its_fuller_closure():
    """The variant carries the least-error support as its closure (and no further
    variant); a closure without one gives none."""
    closure = ClosureFit(np.array([[0.0, 1.0]]), ("1", "h0"), None, 0.3, [],
                         np.array([[0.5, 1.0]]), 0.2)
    proposal = make_dataclass("P", ["closure", "origin"])(closure, "carrier")
    variant = fuller_closure(proposal)
    np.testing.assert_array_equal(variant.closure.coef, [[0.5, 1.0]])
    assert variant.closure.cv_error == 0.2 and variant.closure.fuller is None
    assert variant.origin == "carrier, fuller closure"
    assert fuller_closure(variant) is None


def _driven_context():
    """A damped Duffing oscillator pushed by a slow drive u = F cos(w t), noise-free:
    ydot = -k x - c y - b x^3 + u, x and y observed, as stage two's context (library of
    degree 3); also k, c, b and the drive's series."""
    from scipy.integrate import solve_ivp

    from latentsindy._core.library import feature_expressions
    from latentsindy._stage_two.context import Context

    k, c, b, force, w = 1.2, 0.2, 0.8, 0.9, 0.35

    def rhs(t, s):
        return [s[1], -k * s[0] - c * s[1] - b * s[0] ** 3 + force * np.cos(w * t)]

    t = np.linspace(0.0, 5 * 2 * np.pi / w, 2000)
    x = solve_ivp(rhs, (t[0], t[-1]), [1.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-10).y.T
    lib = ps.PolynomialLibrary(degree=3).fit(x)
    names = lib.get_feature_names(["x", "y"])
    ctx = Context(("x", "y"), tuple(names), tuple(feature_expressions(lib, names, ["x", "y"])),
                  [t], [x], [x], [lib.transform(x)], np.array([1e-4, 1e-4]), [5], 11,
                  np.array([True, True]), 0.05, ps.PolynomialLibrary(degree=2))
    return ctx, (k, c, b), force * np.cos(w * t)


def test_every_constant_back_separates_a_drive_from_the_oscillator():
    """Stage one's structure ``ydot = h`` (its varying coefficient took in -k x - c y
    - b x^3, as it does on the driven-oscillator family): with every term of dy/dt back
    as a constant and the small ones pruned, the smoother's roughness penalty leaves the
    slow drive in h: the oscillator's terms and no others, h following the drive
    (correlation > 0.999), and the drive's rate closing 10x better than stage one's
    structure. The smoother's split is approximate (constants within 20% here; the
    integrated refinement makes them exact, test_benchmark_families). A fixed equation
    gets no such proposal."""
    from dataclasses import replace

    from latentsindy._stage_two.propose.hypotheses import with_every_constant
    from latentsindy._stage_two.propose.proposal import close, evaluate

    ctx, (k, c, b), u = _driven_context()
    support = np.zeros((2, len(ctx.feature_names)), dtype=bool)
    support[0, ctx.feature_names.index("y")] = True
    support[1, 0] = True  # ydot = h(t) * 1 alone
    p = with_every_constant(ctx, support, 1, 0)
    kept = {ctx.feature_names[j] for j in np.flatnonzero(p.structure.support[1])}
    assert kept == {"1", "x", "y", "x^3"}
    found = dict(zip(ctx.feature_names, p.fit.constants[1], strict=True))
    assert found["x"] == pytest.approx(-k, rel=0.2)
    assert found["y"] == pytest.approx(-c, rel=0.2)
    assert found["x^3"] == pytest.approx(-b, rel=0.2)
    assert np.corrcoef(p.hidden[0][:, 0], u)[0, 1] > 0.999
    stage_one = evaluate(single_term(2, len(ctx.feature_names), 1, 0, support), ctx, "s")
    rate, rate_one = (close(q.structure, q.fit, ctx, "rate", 2) for q in (p, stage_one))
    assert rate.score < 0.1 * rate_one.score
    assert with_every_constant(replace(ctx, free_rows=np.array([True, False])), support,
                               1, 0) is None


def test_a_structure_is_evaluated_once_per_context(monkeypatch):
    """``evaluate`` keeps each structure's hidden series and closure per context: the
    same structure again (another origin) costs no new fit and gives the same numbers;
    other loadings are another structure; a context made from this one with
    ``dataclasses.replace`` (the nested discovery's augmented data) starts empty; past
    ``CACHE_BYTES`` nothing more is kept, and the fit is the same."""
    from dataclasses import replace

    from latentsindy._stage_two.propose import proposal

    ctx, _, _ = _driven_context()
    support = np.zeros((2, len(ctx.feature_names)), dtype=bool)
    support[0, ctx.feature_names.index("y")] = True
    support[1, 0] = True
    structure = single_term(2, len(ctx.feature_names), 1, 0, support)
    first = proposal.evaluate(structure, ctx, "first")
    assert len(ctx.evaluated) == 1
    again = proposal.evaluate(structure, ctx, "again")
    assert (again.origin, first.origin) == ("again", "first")
    assert again.fit is first.fit and again.score == first.score
    assert len(ctx.evaluated) == 1
    loads = structure.loadings.copy()
    loads[1, ctx.feature_names.index("x"), 0] = 0.5
    other = proposal.evaluate(Structure(structure.support | (loads[..., 0] != 0), loads,
                                          structure.pivots), ctx, "other")
    assert len(ctx.evaluated) == 2 and other.fit is not first.fit
    rate = proposal.evaluate(structure, ctx, "rate", order=2)
    assert len(ctx.evaluated) == 3 and rate.order == 2
    fresh = replace(ctx, threshold=0.1)
    assert fresh.evaluated == {}
    monkeypatch.setattr(proposal, "CACHE_BYTES", 1000)  # less than one hidden series
    uncached = proposal.evaluate(structure, fresh, "uncached")
    assert fresh.evaluated == {}
    np.testing.assert_array_equal(uncached.hidden[0], first.hidden[0])
    assert uncached.score == first.score


def test_every_pair_of_carriers_of_two_equations_is_one_shared_hidden_state():
    """Two equations with two carriers each: four shared structures, each with the
    first carrier as pivot and the second loaded by the slope of the affine relation of
    their series (2 for h and 2 h + 1); a carrier whose series is not finite gives
    none."""
    t = np.linspace(0, 10, 300)
    h = np.sin(t)
    support = np.zeros((2, 3), dtype=bool)
    support[0, 2] = support[1, 2] = True

    def carrier(i, k, series, score=0.1):
        return SimpleNamespace(structure=single_term(2, 3, i, k, support), score=score,
                               fit=SimpleNamespace(misfit=1.0, hidden=[series[:, None]]))

    every = {0: [carrier(0, 0, h), carrier(0, 1, np.cos(t))],
             1: [carrier(1, 0, 2 * h + 1), carrier(1, 1, h**2),
                 carrier(1, 2, h, score=np.nan)]}
    pairs = carrier_pairs(every, support)
    assert len(pairs) == 4
    assert all(p.n_hidden == 1 and p.pivots[0][0] == 0 for p in pairs)
    (same,) = [p for p in pairs if p.pivots == ((0, 0),) and p.loadings[1, 0, 0] != 0]
    assert same.loadings[0, 0, 0] == 1.0
    assert same.loadings[1, 0, 0] == pytest.approx(2.0, rel=1e-9)
    assert same.support[0, 0] and same.support[1, 0] and same.support[0, 2]


def test_held_out_error_of_a_hopeless_support_does_not_overflow():
    """A target without variance (its variance floored at 1e-300) makes every fold's
    relative error about 1e299, whose square overflows: the spread is still read (0
    for equal folds, finite for unequal ones), with no warning."""
    from latentsindy._stage_two.propose.closure import _cv

    fold = lambda n: (np.eye(1), np.zeros((1, 1)), np.array([float(n)]),  # noqa: E731
                      np.array([float(n)]), n)
    support = np.zeros((1, 1), bool)
    total, se = _cv([fold(10)] * 5, support)
    assert np.isfinite(total) and total > 1e299 and se == 0.0
    total, se = _cv([fold(10)] * 4 + [fold(20)], support)
    assert np.isfinite(total) and 0 < se < total
