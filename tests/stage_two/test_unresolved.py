"""A hidden state whose own dynamics are faster than the sampling is doubted: the data
do not determine its law (it follows the other states quasi-statically)."""

import numpy as np
import pytest
import sympy as sp

from latentsindy._stage_two.doubts.states import UNRESOLVED, unresolved_doubts, unresolved_rate
from latentsindy._stage_two.fit.field import ParametricSystem

X, H, G = sp.symbols("x h g", real=True)


def relaxing(rate):
    """x' = h, h' = -rate h + x: the hidden block of the Jacobian is -rate everywhere."""
    features = (H, X)
    coef = np.array([[1.0, 0.0], [-rate, 1.0]])
    return ParametricSystem(("x", "h"), 1, features, coef, coef != 0)


def turning(omega):
    """x' = h, h' = g, g' = -omega^2 h + x h: the hidden block [[0, 1], [x - omega^2, 0]]
    has eigenvalue moduli sqrt(|x - omega^2|)."""
    features = (H, G, X * H)
    coef = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-omega**2, 0.0, 1.0]])
    return ParametricSystem(("x", "h", "g"), 1, features, coef, coef != 0)


def states(n_states, n_times=200, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(-1.0, 1.0, (n_times, n_states))


@pytest.mark.parametrize("rate", [0.5, 20.0, 400.0])
def test_rate_per_step_is_the_hidden_rate_times_the_step(rate):
    t = np.linspace(0.0, 10.0, 201)  # step 0.05
    per_step, fastest = unresolved_rate(relaxing(rate), [states(2, 201)], [t])
    assert per_step == pytest.approx(rate * 0.05, rel=1e-12)
    assert fastest == 1


def test_rate_is_the_median_over_samples_and_recordings():
    # |x - omega^2| with x = 0 at every sample of one recording, x = 3 in the other
    # (twice as many samples): the median is sqrt(|3 - 1|) = sqrt(2)
    system = turning(1.0)
    first = np.zeros((100, 3))
    second = np.zeros((201, 3))
    second[:, 0] = 3.0
    times = [np.linspace(0, 1, 100), np.linspace(0, 2, 201)]  # steps 1/99 and 0.01
    per_step, fastest = unresolved_rate(system, [first, second], times)
    assert per_step == pytest.approx(np.sqrt(2.0) * 0.01, rel=1e-12)
    # rows of the block: h's has norm 1, g's |x - 1| (1 and 2, median 2): g is fastest
    assert fastest == 2


def test_unsampled_rows_and_systems_without_hidden_states():
    t = np.linspace(0.0, 1.0, 50)
    tr = states(2, 50)
    tr[::2] = np.nan  # a blown-up stretch is left out, not counted as a rate
    per_step, _ = unresolved_rate(relaxing(10.0), [tr], [t])
    assert per_step == pytest.approx(10.0 / 49, rel=1e-12)
    observed_only = ParametricSystem(("x",), 1, (X,), np.array([[-1.0]]), np.array([[True]]))
    per_step, fastest = unresolved_rate(observed_only, [states(1, 50)], [t])
    assert np.isnan(per_step) and fastest is None
    assert unresolved_doubts(observed_only, [states(1, 50)], [t], {}) == ()
    nothing = np.full((50, 2), np.nan)
    assert np.isnan(unresolved_rate(relaxing(10.0), [nothing], [t])[0])
    assert unresolved_doubts(relaxing(10.0), [nothing], [t], {}) == ()


def test_doubt_only_above_one_e_folding_per_step():
    t = np.linspace(0.0, 10.0, 201)  # step 0.05
    below = relaxing(0.9 * UNRESOLVED / 0.05)
    above = relaxing(1.1 * UNRESOLVED / 0.05)
    assert unresolved_doubts(below, [states(2, 201)], [t], {"h": "h0"}) == ()
    (doubt,) = unresolved_doubts(above, [states(2, 201)], [t], {"h": "h0"})
    assert "faster than the sampling" in doubt
    assert "1.1 e-foldings" in doubt and "dh0/dt" in doubt
