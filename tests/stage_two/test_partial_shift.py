"""A hidden state mixed with an observed one: the shift of part of an observed term
that gives the same dynamics with fewer terms is found, exactly, and none is found for
laws that are already the sparsest in their gauge."""

import numpy as np
import pytest
import sympy as sp

from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.rewrite.gauge import partial_shift

X, Y, H = sp.symbols("x y h0", real=True)
R, CURRENT = 0.018, 2.9  # Hindmarsh-Rose's slow rate and current


def system(laws, names=("x", "y", "h0"), n_observed=2):
    """A ParametricSystem holding ``laws`` ({name: polynomial}) exactly."""
    symbols = [sp.Symbol(n, real=True) for n in names]
    rows = [sp.Poly(laws[n], *symbols).as_dict() for n in names]
    monomials = sorted({m for row in rows for m in row}, reverse=True)
    features = tuple(sp.Mul(*[s ** e for s, e in zip(symbols, m, strict=True)])
                     for m in monomials)
    coef = np.array([[float(row.get(m, 0.0)) for m in monomials] for row in rows])
    return ParametricSystem(tuple(names), n_observed, features, coef, coef != 0)


def hindmarsh_rose(mix):
    """Hindmarsh-Rose seen through x and y, its slow current written as h0 = I - z -
    mix y: the truth at mix 0, the same dynamics with two more terms otherwise."""
    z = CURRENT - H - mix * Y  # the true slow current in terms of h0
    ydot = 1 - 5 * X**2 - Y
    zdot = R * (4 * (X + sp.Rational(8, 5)) - z)
    return {"x": sp.expand(Y - X**3 + 3 * X**2 - z + CURRENT),
            "y": ydot, "h0": sp.expand(-zdot - mix * ydot)}


def test_the_mix_of_hindmarsh_rose_draw_2_is_found():
    found = partial_shift(system(hindmarsh_rose(3.5)))
    assert found is not None
    h, shift, laws, before, after = found
    assert h == H and (before, after) == (12, 10)
    assert float(shift / Y) == pytest.approx(3.5, rel=1e-9)
    truth = hindmarsh_rose(0.0)
    for name, law in laws.items():  # the truth's laws, term for term
        got, want = sp.Poly(law, X, Y, H).as_dict(), sp.Poly(truth[name], X, Y, H).as_dict()
        assert set(got) == set(want), name
        for monomial, value in want.items():
            assert float(got[monomial]) == pytest.approx(float(value), rel=1e-9, abs=1e-12)


@pytest.mark.parametrize("laws", [
    hindmarsh_rose(0.0),  # the sparsest form already
    # prey-only Lotka-Volterra (the quick start): no observed term beside the carrier
    # (h - 1 = -beta y has a term fewer, but the hidden state keeps its offset)
    {"x": H * X, "h0": 0.075 * H * X - 1.5 * H - 0.075 * X + 1.5},
    # a logistic prey: the whole shift h + x / K gives as many terms, not fewer
    {"x": H * X - 0.5 * X**2, "h0": 0.6 - 0.6 * H - 0.4 * X + 0.4 * H * X},
], ids=["hindmarsh-rose", "lotka-volterra", "logistic prey"])
def test_laws_sparsest_in_their_gauge_have_none(laws):
    names = tuple(laws)
    assert partial_shift(system(laws, names, len(names) - 1)) is None


def test_a_term_a_shift_only_shrinks_is_kept():
    """Draw 2's law as fitted (the truth under h0 = I - z - 3.5 y to 2%): its constant
    is shrunk by the shift to -0.055, not cancelled, and stays."""
    laws = {"x": H - 0.99808 * X**3 + 2.9919 * X**2 + 4.5046 * Y,
            "y": -4.9627 * X**2 - 0.99514 * Y + 0.98617,
            "h0": -0.018028 * H + 17.382 * X**2 - 0.065749 * X + 3.4222 * Y - 3.5095}
    h, shift, shifted, before, after = partial_shift(system(laws))
    assert (before, after) == (12, 10)
    # the amount that cancels y's coefficient or x^2's: the two agree to 5e-5
    assert float(shift / Y) == pytest.approx(17.382 / 4.9627, rel=1e-4)
    assert sp.Poly(shifted["h0"], X, Y, H).as_dict().keys() == {(1, 0, 0), (0, 0, 0),
                                                               (0, 0, 1)}
    assert float(sp.Poly(shifted["x"], X, Y, H).as_dict()[(0, 1, 0)]) == \
        pytest.approx(4.5046 - float(shift / Y), rel=1e-9)


def test_the_doubt_names_the_shift_and_the_sparser_laws():
    from latentsindy._stage_two.doubts.states import partial_shift_doubts

    mixed = system(hindmarsh_rose(3.5))
    doubt, = partial_shift_doubts(mixed, {"h0": "h"})
    assert doubt.kind == "partial shift"
    assert doubt.startswith("h mixes a hidden variable with an observed one: in h' = h + "
                            "3.5*y the same dynamics have 10 terms instead of 12 (dx/dt = ")
    assert "dh'/dt = " in doubt and "Read the shifted form" in doubt
    assert partial_shift_doubts(system(hindmarsh_rose(0.0)), {"h0": "h"}) == ()


def test_non_polynomial_features_are_left_alone():
    """A law with a Fourier feature has no monomials to cancel: no shift, no error."""
    x, h = sp.symbols("x h0", real=True)
    features = (h, sp.sin(x), x)
    coef = np.array([[1.0, 0.8, 0.3], [0.0, 0.0, -1.0]])
    fourier = ParametricSystem(("x", "h0"), 1, features, coef, coef != 0)
    assert partial_shift(fourier) is None


def test_a_dense_law_saving_one_term_by_chance_is_not_a_mix():
    """Every coefficient of a dense law vanishes at some amount of a shift, which
    saves that one term alone: a gauge mix cancels two or more together."""
    rng = np.random.default_rng(0)
    monomials = [sp.Integer(1), X, Y, H, X**2, X * Y, Y**2, X * H, Y * H, H**2]
    laws = {"x": H + sum(float(rng.normal()) * m for m in (X, Y, X**2)),
            "y": sum(float(rng.normal()) * m for m in monomials if H not in m.free_symbols),
            "h0": sum(float(rng.normal()) * m for m in monomials)}
    assert partial_shift(system(laws)) is None


def test_laws_beyond_the_term_cap_are_not_searched(monkeypatch):
    from latentsindy._stage_two.rewrite import gauge

    mixed = system(hindmarsh_rose(3.5))
    assert partial_shift(mixed) is not None
    monkeypatch.setattr(gauge, "MAX_TERMS", 11)  # the mix has 12
    assert partial_shift(mixed) is None
