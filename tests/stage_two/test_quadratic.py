"""The stacked predictions of term selection's quadratic model are the one-at-a-time
predictions to the bit (so stacking changes no choice of terms)."""

import numpy as np
import pytest

from latentsindy._stage_two.fit.quadratic import Quadratic


def _model(rng, p, share_free):
    """A quadratic model on ``p`` cells with a random normal matrix (scales spread over
    six decades, as coefficients of a polynomial library are) and no fit behind it."""
    x = rng.standard_normal((3 * p, p)) * rng.lognormal(0.0, 3.0, p)
    model = object.__new__(Quadratic)
    model.a = x.T @ x
    model.g = 10 * rng.standard_normal(p)
    model.values = rng.standard_normal(p)
    model.current = rng.random(p) < share_free
    model.cells = [(k % 3, k) for k in range(p)]
    return model


def _bits(values):
    return np.asarray(values, dtype=float).view(np.int64)


@pytest.mark.parametrize("seed", range(6))
def test_stacked_predictions_are_the_single_ones_to_the_bit(seed):
    rng = np.random.default_rng(seed)
    for p in (1, 2, 7, 30, 65):
        model = _model(rng, p, rng.random())
        keeps = []
        for _ in range(150):
            keep = model.current.copy()
            flip = rng.integers(0, p, rng.integers(0, 4))
            keep[flip] = ~keep[flip]
            keeps.append(keep)
        keeps.append(np.zeros(p, dtype=bool))  # nothing kept
        single = [model.predicted(keep) for keep in keeps]
        np.testing.assert_array_equal(_bits(model.predicted_many(keeps)), _bits(single))


def test_a_singular_set_in_a_stack_is_scored_alone_as_before():
    rng = np.random.default_rng(7)
    model = _model(rng, 6, 0.5)
    model.a[:, 2] = model.a[:, 3] = 0.0  # cells 2 and 3 are unidentified
    model.a[2, :] = model.a[3, :] = 0.0
    model.current = np.array([1, 0, 1, 0, 1, 0], dtype=bool)
    # the first two share a stack (two kept, two removed); only 2 and 3 kept is a zero
    # block, which no ridge (a share of its trace) makes solvable
    keeps = [np.array(k, dtype=bool) for k in
             ([0, 1, 1, 0, 0, 0], [0, 0, 1, 1, 0, 0], [0, 1, 0, 0, 0, 1])]
    single = [model.predicted(keep) for keep in keeps]
    assert np.isinf(single[1]) and np.isfinite(single[0])
    np.testing.assert_array_equal(_bits(model.predicted_many(keeps)), _bits(single))


def test_moves_are_listed_and_ranked_as_one_at_a_time():
    rng = np.random.default_rng(3)
    model = _model(rng, 12, 0.4)
    price, s2 = 3.5, 1.7
    base = model.predicted(model.current)
    moves = model.moves(price, s2)
    k0 = int(model.current.sum())
    expected = sorted(((-((model.predicted(keep) - base) / s2 + price * (keep.sum() - k0)),
                        move) for _, move, keep in moves), key=lambda m: -m[0])
    assert [(g, m) for g, m, _ in moves] == expected
    n_in, n_out = k0, 12 - k0
    assert len(moves) == n_in + n_out * (1 + n_in + n_in * (n_in - 1) // 2)
    exchanges = model.exchanges(s2)
    assert all(g == -(model.predicted(keep) - base) / s2 for g, _, keep in exchanges)
    assert [g for g, _, _ in exchanges] == sorted((g for g, _, _ in exchanges), reverse=True)


def test_large_stacks_are_split_and_nothing_changes(monkeypatch):
    from latentsindy._stage_two.fit import quadratic

    rng = np.random.default_rng(11)
    model = _model(rng, 20, 0.5)
    keeps = []
    for _ in range(200):
        keep = model.current.copy()
        flip = rng.integers(0, 20, rng.integers(0, 3))
        keep[flip] = ~keep[flip]
        keeps.append(keep)
    whole = model.predicted_many(keeps)
    monkeypatch.setattr(quadratic, "STACK", 50)  # a set or two per stack
    np.testing.assert_array_equal(_bits(model.predicted_many(keeps)), _bits(whole))
    assert model.predicted_many(np.zeros((0, 20), dtype=bool)).shape == (0,)
