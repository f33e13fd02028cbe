"""Stage two's compiled Runge-Kutta (``compiled.integrate``, the CPU path of a
polynomial field) against the numpy formula it compiles: the same stages and field,
summed in another order, so equal to rounding; a state out of bounds stops both."""

import numpy as np
import pytest
import sympy as sp
import torch

from latentsindy._stage_two.fit import compiled
from latentsindy._stage_two.fit.compiled import sparse_table
from latentsindy._stage_two.fit.field import ParametricSystem
from latentsindy._stage_two.fit.shooting import (
    Batch,
    BlowUp,
    Integrator,
    _hermite,
    _hermite_table,
    make_groups,
    rk4,
)

X, Y, Z = sp.symbols("x y z", real=True)
FEATURES = (sp.Integer(1), X, Y, Z, X * Y, X * Z, Y**2, Z**3)
COEF = np.array([[0.0, -10.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                 [0.0, 28.0, -1.0, 0.0, 0.0, -1.0, 0.0, 0.0],
                 [0.5, 0.0, 0.0, -8.0 / 3.0, 1.0, 0.0, 0.01, -1e-4]])


def _problem():
    system = ParametricSystem(("x", "y", "z"), 1, FEATURES, COEF, COEF != 0)
    t = np.linspace(0.0, 2.0, 200)
    group = make_groups([t], [np.zeros((200, 1))], 0.25, 0.01)[0]
    starts = np.random.default_rng(4).normal([1.0, 1.0, 20.0], 1.0,
                                           size=(group.n_segments, 3))
    return Integrator(system, 1e6), group, starts


def test_sparse_table_keeps_every_nonzero_column_by_column():
    table = np.array([[0.0, 2.0, 0.0], [1.5, 0.0, 0.0], [0.0, -3.0, 0.0]])
    starts, rows, values = sparse_table(table)
    assert starts.tolist() == [0, 1, 3, 3]
    assert rows.tolist() == [1, 0, 2]
    assert values.tolist() == [1.5, 2.0, -3.0]


@pytest.mark.parametrize("sensitivities", [True, False])
def test_compiled_steps_equal_the_numpy_formula_to_rounding(sensitivities):
    """States, sensitivities and slopes at every grid point within 1e-13 of each
    array's scale of numpy's ``rk4`` with the integrator's numpy field (steps of 0.01
    on a Lorenz-like field with a cubic term, 0.25 time units a segment)."""
    integrator, group, starts = _problem()
    assert integrator.in_numpy
    if sensitivities:
        z0 = compiled.with_sensitivities(integrator, starts)
        reference = rk4(integrator._field(COEF), z0, group.grid)
        got = [np.moveaxis(a, 3, 1)
               for a in compiled.states(integrator, COEF, z0, group, True)[:2]]
    else:
        reference = rk4(integrator._plain(COEF), starts, group.grid)
        got = [a[:, :, 0].transpose(0, 2, 1) for a in
               compiled.states(integrator, COEF, starts, group, False)[:2]]
    for a, b in zip(got, reference, strict=True):
        assert a.shape == b.shape
        scale = np.abs(b).max()
        assert np.abs(a - b).max() <= 1e-13 * scale


def test_a_batch_of_segments_on_their_own_steps_matches_them_one_by_one():
    """A (K, G) grid padded with steps of length zero: each row ends where its own grid
    takes it alone, to rounding, and the padding leaves a state as it is, bit for bit."""
    integrator, group, starts = _problem()
    short = np.concatenate([np.linspace(0.0, 0.1, 11), np.full(10, 0.1)])
    grid = torch.as_tensor(np.stack([np.linspace(0.0, 0.2, 21), short]))
    batch = Batch([], grid, torch.zeros(2, 1), np.array([21, 11]))
    z = compiled.states(integrator, COEF, starts[:2], batch, False, batch.steps)[0]
    z = z[:, :, 0].transpose(0, 2, 1)
    alone, _ = rk4(integrator._plain(COEF), starts[1:2], torch.linspace(0.0, 0.1, 11,
                                                                        dtype=torch.float64))
    np.testing.assert_allclose(z[10, 1], alone[-1, 0], rtol=1e-14)
    assert np.array_equal(z[10, 1], z[-1, 1])
    assert batch.steps["compiled", 2].shape == (20, 2)  # made once, kept with the batch


@pytest.mark.parametrize("start", [np.nan, 2e6])
def test_a_state_out_of_bounds_is_a_blow_up(start):
    integrator, group, starts = _problem()
    starts[1, 2] = start
    with pytest.raises(BlowUp):
        integrator.run(COEF, starts, group)
    with pytest.raises(BlowUp):
        integrator.run(COEF * 50.0, starts[[0]], group, sensitivities=False)


@pytest.mark.parametrize("components", [None, 1])
def test_the_compiled_interpolation_is_numpys_bit_for_bit(components):
    """Irregular samples: the compiled Hermite interpolation makes numpy's products
    and sums in numpy's order, so equal to the bit, sensitivities and all."""
    integrator, _, starts = _problem()
    t = np.sort(np.random.default_rng(5).uniform(0.0, 2.0, 150))
    group = make_groups([t], [np.zeros((150, 1))], 0.25, 0.01)[0]
    starts = starts[:group.n_segments]
    k, n = starts.shape
    z0 = compiled.with_sensitivities(integrator, starts)
    z, dz, _ = compiled.states(integrator, COEF, z0, group, True)
    c = n if components is None else components
    rows, _, *weights = _hermite_table(group, "numpy")
    got = compiled.hermite(z, dz, rows, *weights, c).reshape(k, -1, c, z.shape[2])
    zk, dzk = (np.moveaxis(a, 3, 0)[:, :, :c] for a in (z, dz))
    assert np.array_equal(got, _hermite(zk, dzk, group))


def _tensors(part):
    """A run's values or ends: a tensor, or with sensitivities a pair of them."""
    return [part] if isinstance(part, torch.Tensor) else list(part)


@pytest.mark.parametrize("sensitivities", [True, False])
@pytest.mark.parametrize("samples", [200, 20])
def test_a_run_owns_its_results_though_the_trajectories_reuse_one_workspace(
        sensitivities, samples):
    """``Integrator.run`` integrates into a buffer kept between calls: its values and
    ends are its own (a later run from other starts leaves them as they were; one
    segment alone, whose ends are a contiguous slice of the buffer, included) and
    equal the trajectories written into new arrays, bit for bit."""
    integrator, _, starts = _problem()
    t = np.linspace(0.0, 2.0, 200)[:samples]
    group = make_groups([t], [np.zeros((samples, 1))], 0.25, 0.01)[0]
    starts = starts[:group.n_segments]
    kept = integrator.run(COEF, starts, group, sensitivities)
    first = [x.clone() for part in kept for x in _tensors(part)]
    integrator.run(COEF, starts * 0.9, group, sensitivities)  # the same workspace
    for a, b in zip(first, [x for part in kept for x in _tensors(part)], strict=True):
        assert torch.equal(a, b)
    z0 = compiled.with_sensitivities(integrator, starts) if sensitivities else starts
    fresh = compiled.states(integrator, COEF, z0, group, sensitivities)
    reused = compiled.states(integrator, COEF, z0, group, sensitivities, reuse=True)
    assert fresh[2] and reused[2]
    assert np.array_equal(fresh[0], reused[0]) and np.array_equal(fresh[1], reused[1])


@pytest.mark.parametrize("sensitivities", [True, False])
def test_the_polynomial_table_is_the_array_products_to_the_bit(sensitivities):
    """``polynomial_table`` makes in one call the compressed table that the integrator's
    numpy products give (its field, Jacobian and parameter derivatives), every entry
    equal to the bit, in the same order; coefficients that are zero leave no entry."""
    rng = np.random.default_rng(6)
    for free in (COEF != 0, np.ones_like(COEF, bool), np.zeros_like(COEF, bool)):
        system = ParametricSystem(("x", "y", "z"), 1, FEATURES, COEF, free)
        integrator = Integrator(system, 1e6)
        for coef in (COEF, COEF * rng.normal(size=COEF.shape), rng.normal(size=COEF.shape)):
            fm = integrator.features
            got = compiled.polynomial_table(fm.values_table, fm._flat_gradients, coef,
                                            integrator.rows, integrator.cols, sensitivities)
            table = (integrator._polynomial_table(coef) if sensitivities
                     else fm.tables(coef)[0] @ coef.T)
            for a, b in zip(got, sparse_table(table), strict=True):
                assert a.dtype == b.dtype and np.array_equal(a, b)
