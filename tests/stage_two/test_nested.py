"""Pieces of nested discovery (a hidden state inside another's equation)."""

from types import SimpleNamespace

import pytest
import sympy as sp

from latentsindy._stage_two.propose.nested import monomial_name


def test_monomial_names_follow_the_library_convention():
    x, h0 = sp.symbols("x h0", real=True)
    assert monomial_name(x * h0**2, [x, h0]) == "x h0^2"
    assert monomial_name(sp.Integer(1), [x, h0]) == "1"
    assert monomial_name(x, [x, h0]) == "x"


SIGMA, RHO, BETA = 10.0, 28.0, 8.0 / 3.0


def _lorenz_in_a_shifted_gauge(c, k):
    """Lorenz seen through x with both hidden states shifted: h0 = sigma (y - x) - c x
    (so dx/dt = h0 + c x) and h1 = sigma (rho - z - 1) + k x. By substitution and the
    chain rule the same system reads

    dh0/dt = -(1 + s + c) h0 + x h1 - k x^2 - (c (1 + s) + c^2) x,
    dh1/dt = -x h0 - (s + c) x^2 - b h1 + k (b + c) x + k h0 + b s (r - 1).
    """
    import numpy as np

    from latentsindy._stage_two.fit.field import ParametricSystem

    x, h0, h1 = sp.symbols("x h0 h1", real=True)
    features = (h0, x * h1, x**2, x, x * h0, h1, sp.Integer(1))
    laws = [{h0: 1.0, x: c},
            {h0: -(1 + SIGMA + c), x * h1: 1.0, x**2: -k, x: -(c * (1 + SIGMA) + c * c)},
            {x * h0: -1.0, x**2: -(SIGMA + c), h1: -BETA, x: k * (BETA + c), h0: k,
             sp.Integer(1): BETA * SIGMA * (RHO - 1)}]
    coef = np.array([[law.get(f, 0.0) for f in features] for law in laws])
    free = coef != 0
    free[0, 0] = free[1, 1] = False  # the definitions
    system = ParametricSystem(("x", "h0", "h1"), 1, features, coef, free)
    structure = SimpleNamespace(n_hidden=1, pivots=((0, 0),), loadings=np.ones((1, 3, 1)) * [[
        [1.0], [0.0], [0.0]]])
    proposal = SimpleNamespace(order=1, structure=structure, nested=((None, x, None),))
    ctx = SimpleNamespace(feature_exprs=(sp.Integer(1), x, x**2), free_rows=np.array([True]))
    return SimpleNamespace(proposal=proposal, system=system), ctx, (x, h0, h1)


@pytest.mark.parametrize("c, k", [(0.0, 13.0), (2.5, 13.0), (-7.5, 0.0)])
def test_nested_shift_gives_back_the_lorenz_law(c, k):
    """The shifts that absorb c x of dx/dt into h0 and then -k x^2 of dh0/dt into h1
    are c x and -k x, and the shifted system is Lorenz's law in these variables:
    dx/dt = h0, dh0/dt = -(1 + s) h0 + x h1, dh1/dt = -x h0 - b h1 - s x^2 + b s (r - 1),
    the definitions still fixed."""
    from latentsindy._stage_two.propose.nested import shifted_nested_system

    verdict, ctx, (x, h0, h1) = _lorenz_in_a_shifted_gauge(c, k)
    system, shifts = shifted_nested_system(verdict, ctx)
    assert sp.expand(shifts.get(h0, 0) - c * x) == 0
    assert sp.expand(shifts.get(h1, 0) + k * x) == 0
    rhs = system.rhs()
    want = {"x": h0, "h0": -(1 + SIGMA) * h0 + x * h1,
            "h1": -x * h0 - BETA * h1 - SIGMA * x**2 + BETA * SIGMA * (RHO - 1)}
    for name, law in want.items():
        diff = sp.Poly(sp.expand(rhs[name] - law), x, h0, h1)
        assert max((abs(float(v)) for v in diff.coeffs()), default=0.0) < 1e-9, (name, diff)
    assert not system.free[0, system.features.index(h0)]
    assert not system.free[1, system.features.index(x * h1)]


def test_the_nested_shift_alone_when_the_parents_leaves_the_library():
    """dx/dt = h0 + x^2 would move x^2 into h0, whose chain rule puts x^3 into dh1/dt (not
    a feature of the system): the nested state is still shifted out of its flat
    direction, the parent left as it is."""
    from latentsindy._stage_two.propose.nested import shifted_nested_system

    verdict, ctx, (x, h0, h1) = _lorenz_in_a_shifted_gauge(0.0, 13.0)
    system = verdict.system
    coef, free = system.coef.copy(), system.free.copy()
    col = system.features.index(x**2)
    coef[0, col], free[0, col] = 1.0, True
    verdict.system = type(system)(system.state_names, 1, system.features, coef, free)
    shifted, shifts = shifted_nested_system(verdict, ctx)
    assert set(shifts) == {h1} and sp.expand(shifts[h1] + 13.0 * x) == 0
    assert sp.expand(shifted.rhs()["x"] - (h0 + x**2)) == 0
    assert x**2 not in sp.Poly(shifted.rhs()["h0"], x, h0, h1).as_expr().as_coefficients_dict()


def test_nested_system_already_in_its_gauge_is_left_alone():
    from latentsindy._stage_two.propose.nested import shifted_nested_system

    verdict, ctx, _ = _lorenz_in_a_shifted_gauge(0.0, 0.0)
    assert shifted_nested_system(verdict, ctx) is None


def _trial(misfit, hidden, nested=(), system=None):
    fit = SimpleNamespace(residual_variance=misfit, system=system)
    return SimpleNamespace(proposal=SimpleNamespace(n_states=1, hidden=hidden, nested=nested),
                           fit=fit)


def test_nested_parents_have_distinct_hidden_series():
    """A proposal and its fuller-closure variant share their hidden series, hence their
    nested proposals: the second place goes to the next series, best misfit first."""
    import numpy as np

    from latentsindy._stage_two.judge import _distinct_parents

    a, b = [np.arange(4.0)[:, None]], [np.arange(4.0)[:, None] ** 2]
    trials = [_trial(5.0, b), _trial(1.0, a), _trial(2.0, [a[0].copy()]), _trial(9.0, b)]
    chosen = _distinct_parents(trials, 2)
    assert [t.fit.residual_variance for t in chosen] == [1.0, 5.0]


def test_a_repeated_nested_system_is_judged_once():
    """Nested trials whose systems have the same terms (every candidate free) keep only
    the better fit; other trials are never removed."""
    import numpy as np

    from latentsindy._stage_two.fit.field import ParametricSystem
    from latentsindy._stage_two.judge import _without_repeats

    x, h0, h1 = sp.symbols("x h0 h1", real=True)
    features = (h0, x * h1, x)
    free = np.array([[False, False, True], [True, False, True], [True, True, True]])

    def system(scale):
        return ParametricSystem(("x", "h0", "h1"), 1, features, scale * free, free)

    nested = ((None, x, None),)
    worse, better = _trial(3.0, [], nested, system(1.0)), _trial(2.0, [], nested, system(2.0))
    plain = [_trial(4.0, [], (), system(1.0)), _trial(4.0, [], (), system(1.0))]
    kept = _without_repeats([worse, *plain, better])
    assert kept == [*plain, better]
