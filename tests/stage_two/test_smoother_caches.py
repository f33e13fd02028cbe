"""What the structured smoother keeps between fits: its operators per sampling and its
weighted integrals per weights; a fit from kept pieces is the fit made afresh, bit for
bit."""

import warnings

import numpy as np
import scipy.sparse as sps

from latentsindy import systems
from latentsindy._stage_two.propose import smoother
from latentsindy._stage_two.propose.smoother import fit_hidden, single_term


def _sigma(x):
    return np.full(x.shape[1], 1e-3) * x.std(axis=0)


def test_the_smoothers_operators_are_made_once_per_sampling(monkeypatch):
    """The smoother's operators (segment integrals, anchors, knot interpolation) depend
    only on the sample times and the knot spacing: a second fit on the same times (in
    another array) reuses them, and the fit is the same to the bit; other times or
    another spacing get their own, and only the last ``_KEEP`` samplings are held."""
    monkeypatch.setattr(smoother, "_OPERATORS", {})
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=600)
    x = data.x_clean[:, :1]
    st = single_term(1, 1, 0, 0, np.zeros((1, 1), dtype=bool))
    first = fit_hidden(st, [x], [x], [data.t], _sigma(x), 2)
    (made,) = smoother._OPERATORS.values()
    again = fit_hidden(st, [x], [x], [data.t.copy()], _sigma(x), 2)
    assert smoother._OPERATORS[next(iter(smoother._OPERATORS))] is made
    assert np.array_equal(first.hidden[0], again.hidden[0])
    fresh = smoother._trajectory_operators(np.asarray(data.t, float), 2)
    for held, new in zip(made[0], fresh, strict=True):
        assert (held != new).nnz == 0
    fit_hidden(st, [x], [x], [data.t], _sigma(x), 3)
    fit_hidden(st, [x[:500]], [x[:500]], [data.t[:500]], _sigma(x), 2)
    assert len(smoother._OPERATORS) == smoother._KEEP


def test_the_smoothers_weighted_integrals_are_made_once_per_weights():
    """A second structure whose hidden state loads on the same term with the same weight
    reuses the weighted integral ``q @ diag(g) @ interp`` (the same object), and the
    fit is the same to the bit as one made afresh; other weights or other operators get
    their own product, equal to the sparse products' in every digit; at most
    ``_KEEP_PRODUCTS`` are held."""
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=600)
    x = data.x_clean[:, :1]
    st = single_term(1, 1, 0, 0, np.zeros((1, 1), dtype=bool))
    first = fit_hidden(st, [x], [x], [data.t], _sigma(x), 2)
    assert len(smoother._PRODUCTS) == 1
    (made,) = smoother._PRODUCTS.values()
    again = fit_hidden(st, [x], [x], [data.t], _sigma(x), 2)
    assert list(smoother._PRODUCTS.values()) == [made]
    smoother._PRODUCTS.clear()
    afresh = fit_hidden(st, [x], [x], [data.t], _sigma(x), 2)
    assert np.array_equal(first.hidden[0], again.hidden[0])
    assert np.array_equal(first.hidden[0], afresh.hidden[0])
    q, _, interp = smoother._operators([data.t], [2])[0]
    rng = np.random.default_rng(0)
    for _ in range(smoother._KEEP_PRODUCTS + 2):
        g = rng.standard_normal(len(data.t))
        got = smoother._weighted_integral(q, g, interp)
        want = q @ sps.diags(g) @ interp
        assert got.shape == want.shape and (got != want).nnz == 0
        assert smoother._weighted_integral(q, g.copy(), interp) is got
    assert len(smoother._PRODUCTS) == smoother._KEEP_PRODUCTS
    other = smoother._operators([data.t[:500]], [2])[0]
    assert smoother._weighted_integral(other[0], g[:500], other[2]).shape[0] == 500


def test_a_weighted_integral_is_told_apart_by_its_operators_and_its_weights_type():
    """The same weights with other operators (another spacing, the same samples), and
    weights whose bytes are those of other values (int64 against float64), get their
    own products, each the sparse products' to the bit; products whose operators are
    no longer kept are dropped, and a product used again is kept longest."""
    t = np.linspace(0.0, 10.0, 400)
    q2, _, b2 = smoother._operators([t], [2])[0]
    q3, _, b3 = smoother._operators([t], [3])[0]
    g = np.random.default_rng(1).standard_normal(len(t))
    for q, b in ((q2, b2), (q3, b3)):
        got = smoother._weighted_integral(q, g, b)
        assert got.shape == (len(t), b.shape[1])
        assert (got != q @ sps.diags(g) @ b).nnz == 0
    assert smoother._weighted_integral(q2, g, b2).shape != smoother._weighted_integral(
        q3, g, b3).shape
    as_int = g.view(np.int64)
    with warnings.catch_warnings():  # scipy: integer weights, a float product (for now)
        warnings.simplefilter("ignore", FutureWarning)
        got = smoother._weighted_integral(q2, as_int, b2)
        assert (got != q2 @ sps.diags(as_int) @ b2).nnz == 0
    assert (got != smoother._weighted_integral(q2, g, b2)).nnz > 0
    oldest = next(iter(smoother._PRODUCTS))
    assert oldest[0] == id(q3) and len(smoother._PRODUCTS) == 3
    smoother._weighted_integral(q3, g, b3)  # the oldest, used again: now the newest
    assert list(smoother._PRODUCTS)[-1] == oldest and len(smoother._PRODUCTS) == 3
    smoother._operators([t[:300]], [2])  # q2's operators are no longer kept
    smoother._weighted_integral(q3, g + 1.0, b3)
    assert all(v[0] is q3 for v in smoother._PRODUCTS.values())
