"""Closed-loop refinement: features, multiple shooting, standard errors, term selection,
held-out scores and the choice among structures, against analytic truth."""

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest
import sympy as sp
import torch
from scipy.integrate import solve_ivp

from latentsindy import systems
from latentsindy._core.coloured import ar1_noise
from latentsindy._core.derivatives import noise_level
from latentsindy._stage_two import judge
from latentsindy._stage_two.doubts.checks import doubts, segment_constant_doubts
from latentsindy._stage_two.doubts.terms import missing_doubts, weak_doubts
from latentsindy._stage_two.fit import terms as terms_module
from latentsindy._stage_two.fit.field import FeatureMap, ParametricSystem
from latentsindy._stage_two.fit.held_out import cross_validate
from latentsindy._stage_two.fit.least_squares import HOPELESS, GiveUpWatch
from latentsindy._stage_two.fit.normal_equations import DENSE, NormalEquations, as_array, solve
from latentsindy._stage_two.fit.refine import JOIN, Fit, Problem
from latentsindy._stage_two.fit.shooting import BlowUp
from latentsindy._stage_two.fit.terms import (
    AMBIGUITY,
    ambiguities,
    missing_terms,
    select_terms,
    weak_terms,
)
from latentsindy._stage_two.judge import paired_evidence, rank
from latentsindy._stage_two.result_parts import Refinement, Term
from latentsindy._stage_two.verdict import Trial, Verdict, finish

X, Y, Z, H = sp.symbols("x y z h", real=True)
A, B, G, D = 1.0, 0.1, 1.5, 0.075
LV_FEATURES = (X * H, sp.Integer(1), H, X, H * X**2)


def lv_system(hidden_row, free_row=None):
    """x' = x h (the definition, fixed); h' = hidden_row . (x h, 1, h, x, h x^2)."""
    coef = np.zeros((2, 5))
    coef[0, 0] = 1.0
    coef[1] = hidden_row
    free = np.zeros((2, 5), dtype=bool)
    free[1] = hidden_row != 0 if free_row is None else free_row
    return ParametricSystem(("x", "h"), 1, LV_FEATURES, coef, free)


TRUTH_ROW = np.array([D, A * G, -G, -A * D, 0.0])  # h' = delta x h + a g - g h - a d x


def lv_problem(noise, seed=0, n_times=1500):
    data = systems.lotka_volterra(A, B, G, D, n_times=n_times, t_end=15.0, noise=noise,
                                  seed=seed)
    h_true = A - B * data.x_clean[:, 1]
    guesses = [np.column_stack([data.x_clean[:, 0], h_true])]
    return data, guesses


def swapped_lv_problem():
    """1% noise, the true x h term missing and a spurious h x^2 in its place; returns
    the problem and the terms selection may add."""
    data, guesses = lv_problem(0.01)
    row = TRUTH_ROW.copy()
    row[0], row[4] = 0.0, 1e-3
    problem = Problem(lv_system(row), [data.t], [data.x[:, :1]], guesses)
    candidates = np.zeros((2, 5), dtype=bool)
    candidates[1] = True
    return problem, candidates & ~problem.system.free


def test_feature_map_monomials_match_lambdify():
    """The exponent path (monomials) and the lambdify path give the same features and
    gradients; a non-polynomial feature goes through lambdify."""
    feats = [sp.Integer(1), X, X**2 * Y, Y**3, X * Y * Z]
    fast = FeatureMap(feats, [X, Y, Z])
    slow = FeatureMap(feats + [sp.sin(X)], [X, Y, Z])
    assert fast.exponents is not None and slow.exponents is None
    y = torch.randn(7, 3, dtype=torch.float64)
    phi_f, dphi_f = fast(y)
    phi_s, dphi_s = slow(y)
    torch.testing.assert_close(phi_f, phi_s[:, :5])
    torch.testing.assert_close(dphi_f, dphi_s[:, :5])
    torch.testing.assert_close(phi_s[:, 5], torch.sin(y[:, 0]))
    torch.testing.assert_close(dphi_s[:, 5, 0], torch.cos(y[:, 0]))


def test_polynomial_field_matches_the_general_path():
    """The sensitivity equations from the monomial tables (one matrix product) equal
    the feature map's general path (lambdify, forced by an extra sin feature with a zero
    fixed coefficient): states and sensitivities to start and coefficients, on the
    sample grid and at the segment ends."""
    from latentsindy._stage_two.fit.shooting import Integrator, make_groups

    feats = (sp.Integer(1), X, Y, Z, X * Y, X * Z, Y**2 * Z)
    coef = np.array([[0.0, -10.0, 10.0, 0.0, 0.0, 0.0, 0.01],
                     [0.0, 28.0, -1.0, 0.0, 0.0, -1.0, 0.0],
                     [1.0, 0.0, 0.0, -8.0 / 3.0, 1.0, 0.0, 0.0]])
    free = coef != 0
    poly = ParametricSystem(("x", "y", "z"), 2, feats, coef, free)
    general = ParametricSystem(("x", "y", "z"), 2, feats + (sp.sin(X),),
                               np.hstack([coef, np.zeros((3, 1))]),
                               np.hstack([free, np.zeros((3, 1), bool)]))
    t = np.linspace(0.0, 2.0, 200)
    group = make_groups([t], [np.zeros((200, 2))], 0.25, 0.01)[0]
    starts = np.random.default_rng(1).normal([1.0, 1.0, 20.0], 1.0, size=(group.n_segments, 3))
    fast, slow = Integrator(poly, 1e6), Integrator(general, 1e6)
    assert fast.features.exponents is not None and slow.features.exponents is None
    for with_sens in (True, False):
        a = fast.run(coef, starts, group, sensitivities=with_sens)
        b = slow.run(general.coef, starts, group, sensitivities=with_sens)
        for u, v in zip(torch.utils._pytree.tree_leaves(a), torch.utils._pytree.tree_leaves(b),
                        strict=True):
            torch.testing.assert_close(u, v, rtol=1e-12, atol=1e-10)


def test_numpy_and_torch_integrate_a_polynomial_field_alike():
    """On the CPU a polynomial field is integrated in numpy; on a GPU the same code runs
    in torch (CI has no GPU, so the torch path is forced here): states and
    sensitivities equal to 1e-12, with and without sensitivities; a blow-up is reported
    by both."""
    from latentsindy._stage_two.fit.shooting import Integrator, make_groups

    feats = (sp.Integer(1), X, Y, Z, X * Y, X * Z)
    coef = np.array([[0.0, -10.0, 10.0, 0.0, 0.0, 0.0],
                     [0.0, 28.0, -1.0, 0.0, 0.0, -1.0],
                     [0.0, 0.0, 0.0, -8.0 / 3.0, 1.0, 0.0]])
    system = ParametricSystem(("x", "y", "z"), 1, feats, coef, coef != 0)
    t = np.linspace(0.0, 2.0, 200)
    group = make_groups([t], [np.zeros((200, 1))], 0.25, 0.01)[0]
    starts = np.random.default_rng(2).normal([1.0, 1.0, 20.0], 1.0, size=(group.n_segments, 3))
    fast, slow = Integrator(system, 1e6), Integrator(system, 1e6)
    slow.in_numpy = False
    assert fast.in_numpy
    for with_sens in (True, False):
        a = fast.run(coef, starts, group, sensitivities=with_sens)
        b = slow.run(coef, starts, group, sensitivities=with_sens)
        for u, v in zip(torch.utils._pytree.tree_leaves(a), torch.utils._pytree.tree_leaves(b),
                        strict=True):
            assert u.dtype == v.dtype == torch.float64
            torch.testing.assert_close(u, v, rtol=1e-12, atol=1e-10)
    for integrator in (fast, slow):
        with pytest.raises(BlowUp):
            integrator.run(coef * 50.0, starts, group)


def test_an_integration_interpolates_only_the_states_asked_for():
    """``components`` restricts the interpolation to the first states (the observed
    ones): their values and sensitivities are those of the whole run, digit for digit,
    the segment ends hold every state, in numpy and in torch; the interpolation table
    made at the first run of a group serves the next runs unchanged."""
    from latentsindy._stage_two.fit.shooting import Integrator, make_groups

    feats = (sp.Integer(1), X, Y, Z, X * Y, X * Z)
    coef = np.array([[0.0, -10.0, 10.0, 0.0, 0.0, 0.0],
                     [0.0, 28.0, -1.0, 0.0, 0.0, -1.0],
                     [0.0, 0.0, 0.0, -8.0 / 3.0, 1.0, 0.0]])
    system = ParametricSystem(("x", "y", "z"), 1, feats, coef, coef != 0)
    t = np.sort(np.random.default_rng(3).uniform(0.0, 2.0, 150))  # irregular samples
    group = make_groups([t], [np.zeros((150, 1))], 0.25, 0.01)[0]
    starts = np.random.default_rng(2).normal([1.0, 1.0, 20.0], 1.0, size=(group.n_segments, 3))
    numpy_path, torch_path = Integrator(system, 1e6), Integrator(system, 1e6)
    torch_path.in_numpy = False
    leaves = torch.utils._pytree.tree_leaves
    for integrator in (numpy_path, torch_path):
        for with_sens in (True, False):
            whole = integrator.run(coef, starts, group, sensitivities=with_sens)
            for c in (0, 1, 2):
                part = integrator.run(coef, starts, group, sensitivities=with_sens,
                                      components=c)
                (v_whole, e_whole), (v_part, e_part) = ((whole[0], whole[1]),
                                                        (part[0], part[1]))
                for u, v in zip(leaves(v_whole), leaves(v_part), strict=True):
                    assert v.shape[2] == c
                    torch.testing.assert_close(v, u[:, :, :c], rtol=0, atol=0)
                for u, v in zip(leaves(e_whole), leaves(e_part), strict=True):
                    torch.testing.assert_close(v, u, rtol=0, atol=0)
    assert set(map(str, group.hermite)) == {"numpy", "cpu"}  # one table per path
    again = numpy_path.run(coef, starts, group, components=1)
    first = numpy_path.run(coef, starts, group, components=1)
    for u, v in zip(leaves(again), leaves(first), strict=True):
        torch.testing.assert_close(u, v, rtol=0, atol=0)
    values, _ = numpy_path.run(coef, starts, group, sensitivities=False, components=1)
    exact = solve_ivp(lambda _, y: coef @ np.array([1.0, *y, y[0] * y[1], y[0] * y[2]]),
                      (0.0, float(group.grid[-1])), starts[0], rtol=1e-10, atol=1e-10,
                      t_eval=group.positions[0][group.mask[0]].numpy())
    np.testing.assert_allclose(values[0, group.mask[0], 0].numpy(), exact.y[0], rtol=1e-4,
                               atol=1e-3)


def test_single_thread_covers_torch_and_the_blas():
    """Stage two's small algebra runs on one thread, torch's and the BLAS's, and both
    are restored afterwards."""
    from threadpoolctl import threadpool_info

    from latentsindy._core.threads import single_thread

    def blas():
        return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]

    before, torch_before = blas(), torch.get_num_threads()
    with single_thread():
        assert torch.get_num_threads() == 1 and set(blas()) == {1}
    assert blas() == before and torch.get_num_threads() == torch_before


def _arrow_equations(n_free, k=700, n=2, seed=2):
    """Normal equations of ``k`` segments (free coefficients coupling everything, each
    start its own segment and, through continuity, its neighbours'), held by blocks."""
    rng = np.random.default_rng(seed)
    eq = NormalEquations(n_free, k, n)
    eq.add(rng.normal(size=(k, 9, n_free + n)), rng.normal(size=(k, 9)), np.arange(k)[:, None])
    pairs = np.stack([np.arange(k - 1), np.arange(1, k)], axis=1)
    eq.add(rng.normal(size=(k - 1, n, n_free + 2 * n)), rng.normal(size=(k - 1, n)), pairs)
    return eq


def test_damped_solves_of_small_systems_leave_the_matrix_as_it_was():
    """Levenberg-Marquardt's damped solve of a small (dense) system is the solve of the
    damped matrix, and leaves the matrix as it was (one point's matrix serves all of
    its damped solves)."""
    from scipy.linalg import block_diag

    rng = np.random.default_rng(0)
    blocks = [rng.normal(size=(4, 4)) for _ in range(DENSE // 16)]
    matrix = block_diag(*[b @ b.T + np.eye(4) for b in blocks])
    rhs, damping = rng.normal(size=len(matrix)), rng.uniform(0.1, 2.0, size=len(matrix))
    before = matrix.copy()
    np.testing.assert_allclose(solve(matrix, rhs, damping),
                               np.linalg.solve(before + np.diag(damping), rhs), rtol=1e-10,
                               atol=1e-12)
    np.testing.assert_allclose(solve(matrix, rhs), np.linalg.solve(before, rhs), rtol=1e-10,
                               atol=1e-12)
    np.testing.assert_array_equal(matrix, before)


@pytest.mark.parametrize("n_free", [0, 6])
@pytest.mark.parametrize("n", [1, 2, 3])
def test_large_arrow_systems_are_solved_through_their_banded_starts(n_free, n):
    """Large normal equations are held by their blocks (ArrowMatrix) and solved through
    the banded starts' block and the Schur complement: damped or not, one right-hand
    side or several, they agree with the dense solve and leave the matrix as it was;
    the dense and sparse forms of the blocks are the same matrix."""
    from latentsindy._stage_two.fit.normal_equations import ArrowMatrix

    rng = np.random.default_rng(4)
    eq = _arrow_equations(n_free, n=n)
    matrix = eq.matrix()
    assert isinstance(matrix, ArrowMatrix) and matrix.shape[0] > DENSE
    dense = matrix.toarray()
    np.testing.assert_array_equal(dense, dense.T)
    np.testing.assert_array_equal(matrix.tosparse().toarray(), dense)
    np.testing.assert_array_equal(matrix.diagonal(), np.diag(dense))
    damping = rng.uniform(0.1, 2.0, size=dense.shape[0])
    rhs = rng.normal(size=(dense.shape[0], 3))
    np.testing.assert_allclose(solve(matrix, rhs[:, 0], damping),
                               np.linalg.solve(dense + np.diag(damping), rhs[:, 0]),
                               rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(solve(matrix, rhs), np.linalg.solve(dense, rhs),
                               rtol=1e-8, atol=1e-10)
    np.testing.assert_array_equal(matrix.toarray(), dense)


def test_an_arrow_system_whose_starts_block_is_not_positive_definite_is_solved_by_lu():
    """Where the starts' block is indefinite (its banded Cholesky factor fails), the
    general sparse solver gives the same solution as the dense one."""
    eq = _arrow_equations(3, k=320)
    matrix = eq.matrix()
    matrix.diag[5] -= 50.0 * np.eye(2)  # indefinite, still invertible
    dense = matrix.toarray()
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        matrix.starts_solve(np.ones(dense.shape[0] - 3))
    rng = np.random.default_rng(5)
    rhs, damping = rng.normal(size=dense.shape[0]), rng.uniform(0.1, 2.0, dense.shape[0])
    np.testing.assert_allclose(solve(matrix, rhs), np.linalg.solve(dense, rhs),
                               rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(solve(matrix, rhs, damping),
                               np.linalg.solve(dense + np.diag(damping), rhs),
                               rtol=1e-8, atol=1e-10)


def test_singular_arrow_systems_raise_as_the_dense_solve_does():
    """A singular system held by blocks (a start no residual touches) raises numpy's
    LinAlgError, as the dense solve does, not a warning and NaN; the covariance of
    such a fit is then NaN, as for a small system."""
    from latentsindy._stage_two.fit.least_squares import covariance

    eq = _arrow_equations(2)
    matrix = eq.matrix()
    matrix.diag[3] = 0.0
    matrix.coupling[3] = 0.0
    matrix.upper[2] = 0.0
    matrix.upper[3] = 0.0
    with pytest.raises(np.linalg.LinAlgError, match="singular"):
        solve(matrix, np.ones(matrix.shape[0]))
    assert np.all(np.isfinite(solve(matrix, np.ones(matrix.shape[0]),
                                    np.ones(matrix.shape[0]))))
    eq.matrix = lambda: matrix
    assert np.all(np.isnan(covariance(eq, 2)))


@pytest.mark.parametrize("where", ["coefficient", "start"])
def test_normal_equations_with_a_non_finite_entry_solve_to_nan_on_both_paths(monkeypatch, where):
    """A point whose sensitivities overflowed gives normal equations with NaN: the dense
    solve and the solve by blocks both return NaN (Levenberg-Marquardt then rejects
    the step), neither raises."""
    from latentsindy._stage_two.fit import normal_equations

    steps = []
    for dense in (True, False):
        monkeypatch.setattr(normal_equations, "DENSE", 10**6 if dense else 0)
        rng = np.random.default_rng(7)
        eq = NormalEquations(4, 30, 3)
        jac = rng.normal(size=(30, 9, 7))
        jac[12, 3, 1 if where == "coefficient" else 5] = np.nan
        eq.add(jac, rng.normal(size=(30, 9)), np.arange(30)[:, None])
        matrix = eq.matrix()
        assert isinstance(matrix, normal_equations.ArrowMatrix) != dense
        steps.append(solve(matrix, -eq.grad, 1e-3 * np.abs(matrix.diagonal())))
    assert np.isnan(steps[0]).any() and np.isnan(steps[1]).all()


def test_systems_beyond_a_hundred_unknowns_are_held_by_blocks():
    """The switch between the two forms sits at ``DENSE`` = 100 unknowns, where their
    costs cross (a two-state system of 40 segments dense, a three-state one by blocks)."""
    from latentsindy._stage_two.fit.normal_equations import ArrowMatrix

    assert DENSE == 100
    assert isinstance(NormalEquations(6, 40, 2).matrix(), np.ndarray)  # 86 unknowns
    assert isinstance(NormalEquations(10, 40, 3).matrix(), ArrowMatrix)  # 130 unknowns


def test_arrow_blocks_take_only_consecutive_pairs_of_segments():
    """A block touching two segments that are not neighbours has no place in the arrow:
    an error that says so, not a wrong matrix, and the equations are left as they
    were; so are blocks beyond the last segment and Gram blocks of the wrong shape."""
    from latentsindy._stage_two.fit.normal_equations import ArrowMatrix

    eq = NormalEquations(0, 400, 2)
    eq.add(np.ones((1, 2, 4)), np.ones((1, 2)), np.array([[0, 1]]))
    before = (eq.cost, eq.grad.copy(), eq.matrix().diag.copy(), eq.matrix().upper.copy())
    with pytest.raises(ValueError, match="consecutive"):
        eq.add(np.ones((1, 2, 4)), np.ones((1, 2)), np.array([[0, 2]]))
    with pytest.raises(IndexError, match="segments 399..400 for a matrix of 400"):
        eq.add(np.ones((1, 2, 4)), np.ones((1, 2)), np.array([[399, 400]]))
    assert eq.cost == before[0] and np.array_equal(eq.grad, before[1])
    assert np.array_equal(eq.matrix().diag, before[2])
    assert np.array_equal(eq.matrix().upper, before[3])
    arrow = ArrowMatrix.zeros(2, 10, 2)
    with pytest.raises(ValueError, match=r"expected \(1, 6, 6\)"):
        arrow.add(np.ones((1, 4, 4)), np.array([[3, 4]]))
    with pytest.raises(IndexError, match="segments -1..-1"):
        arrow.add(np.ones((1, 4, 4)), np.array([[-1]]))
    assert not arrow.toarray().any()


def _arrow_add_by_arrays(arrow, gram, segments):
    """ArrowMatrix.add as array operations (the code the compiled loop replaced)."""
    p, n, first = arrow.p, arrow.n, segments[:, 0]
    arrow.border += gram[:, :p, :p].sum(axis=0)
    for j in range(segments.shape[1]):
        rows = slice(p + j * n, p + (j + 1) * n)
        np.add.at(arrow.coupling, first + j, gram[:, rows, :p])
        np.add.at(arrow.diag, first + j, gram[:, rows, rows])
    if segments.shape[1] == 2:
        np.add.at(arrow.upper, first, gram[:, p:p + n, p + n:])


@pytest.mark.parametrize("order", ["increasing", "shuffled", "repeated"])
def test_arrow_blocks_are_added_as_the_array_operations_add_them_to_the_bit(order):
    """The compiled addition of Gram blocks (segments in increasing order), the indexed
    one (distinct, in any order) and ``np.add.at`` (repeats) give the array operations'
    sums bit for bit, on magnitudes spread over 16 decades where any change of order
    would show; one free coefficient included (numpy sums the border pairwise then)."""
    from latentsindy._stage_two.fit.normal_equations import ArrowMatrix

    rng = np.random.default_rng(7)
    for p, n, k, m in [(1, 2, 34, 2), (1, 1, 30, 1), (0, 2, 20, 2), (6, 2, 50, 2),
                       (10, 3, 40, 1), (4, 4, 9, 2)]:
        blocks = [rng.normal(size=s) for s in [(p, p), (k, n, p), (k, n, n), (k - 1, n, n)]]
        ours = ArrowMatrix(*(b.copy() for b in blocks))
        theirs = ArrowMatrix(*(b.copy() for b in blocks))
        for _ in range(3):
            n_blocks = int(rng.integers(1, k - m + 2))
            first = np.sort(rng.choice(k - m + 1, n_blocks, replace=False))
            if order == "shuffled":
                first = rng.permutation(first)
            elif order == "repeated":
                first = rng.permutation(np.concatenate([first, first[:2]]))
            segments = first[:, None] + np.arange(m)[None]
            size = p + n * m
            gram = rng.normal(size=(len(first), size, size)) * 10.0 ** rng.integers(
                -8, 8, size=(len(first), 1, 1))
            ours.add(gram, segments)
            _arrow_add_by_arrays(theirs, gram, segments)
        for a, b in zip([ours.border, ours.coupling, ours.diag, ours.upper],
                        [theirs.border, theirs.coupling, theirs.diag, theirs.upper],
                        strict=True):
            assert np.array_equal(a, b)


@pytest.mark.parametrize("n_free", [0, 5])
def test_term_selection_eliminates_large_starts_blocks_through_their_band(n_free):
    """The coefficients' Schur complement as term selection makes it, of 700 segments
    held by blocks: the same as eliminating the starts of the dense matrix."""
    from latentsindy._stage_two.fit.quadratic import _eliminated

    eq = _arrow_equations(n_free, seed=3)
    a, g = eq.matrix().toarray(), eq.grad
    p = n_free
    x = np.linalg.solve(a[p:, p:], np.column_stack([a[p:, :p], g[p:]]))
    schur, reduced = _eliminated(eq.matrix(), g, p)
    np.testing.assert_allclose(schur, a[:p, :p] - a[:p, p:] @ x[:, :p], rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(reduced, g[:p] - a[:p, p:] @ x[:, p], rtol=1e-7, atol=1e-8)
    small = _eliminated(a, g, p)  # the dense form's own path
    np.testing.assert_allclose(small[0], schur, rtol=1e-7, atol=1e-8)
    blocks = eq.matrix()
    blocks.diag[7] -= 50.0 * np.eye(2)  # indefinite: the sparse LU's path
    a = blocks.toarray()
    x = np.linalg.solve(a[p:, p:], np.column_stack([a[p:, :p], g[p:]]))
    schur, reduced = _eliminated(blocks, g, p)
    np.testing.assert_allclose(schur, a[:p, :p] - a[:p, p:] @ x[:, :p], rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(reduced, g[:p] - a[:p, p:] @ x[:, p], rtol=1e-7, atol=1e-8)


def test_normal_equations_dense_and_sparse_assemble_the_same_system(monkeypatch):
    """The arrow-structured J^T J and J^T r, assembled densely (small systems) and by
    blocks (large ones), equal the products of the whole Jacobian written out, blocks
    that touch one segment twice in an addition included."""
    from latentsindy._stage_two.fit import normal_equations

    rng = np.random.default_rng(1)
    p, k, n = 3, 5, 2
    data = [(rng.normal(size=(k, 7, p + n)), rng.normal(size=(k, 7)), np.arange(k)[:, None]),
            (rng.normal(size=(k - 1, n, p + 2 * n)), rng.normal(size=(k - 1, n)),
             np.stack([np.arange(k - 1), np.arange(1, k)], axis=1)),
            (rng.normal(size=(3, 4, p + n)), rng.normal(size=(3, 4)), np.array([[0], [0], [3]]))]
    full, resid = [], []  # the whole Jacobian, row by row
    for jac, r, segs in data:
        for b in range(len(jac)):
            cols = np.concatenate([np.arange(p)] + [p + s * n + np.arange(n) for s in segs[b]])
            rows = np.zeros((jac.shape[1], p + k * n))
            rows[:, cols] = jac[b]
            full.append(rows)
            resid.append(r[b])
    full, resid = np.vstack(full), np.concatenate(resid)
    jac0, r0, segs0 = data[0]
    first = np.zeros(p + k * n)  # the gradient of the first blocks alone
    for b in range(len(jac0)):
        cols = np.concatenate([np.arange(p), p + segs0[b, 0] * n + np.arange(n)])
        first[cols] += jac0[b].T @ r0[b]
    for dense in (True, False):
        monkeypatch.setattr(normal_equations, "DENSE", 10**6 if dense else 0)
        empty = NormalEquations(p, k, n)
        assert not np.any(as_array(empty.matrix())) and not np.any(empty.grad)
        eq = NormalEquations(p, k, n)
        for i, (jac, r, segs) in enumerate(data):
            eq.add(jac, r, segs)
            if i == 0:  # read between additions: the next addition is not missed
                np.testing.assert_allclose(eq.grad, first, rtol=1e-12, atol=1e-12)
        assert isinstance(eq.matrix(), np.ndarray) == dense
        np.testing.assert_allclose(as_array(eq.matrix()), full.T @ full, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(eq.grad, full.T @ resid, rtol=1e-12, atol=1e-12)
        assert eq.cost == pytest.approx(float(resid @ resid), rel=1e-12)


def test_stopping_at_the_resolution_stays_within_a_fraction_of_a_standard_error():
    """The fit stops once the next step would gain less than ``RESOLUTION`` noise
    variances: on prey-only LV at 1% noise its coefficients agree with a fit run to the
    relative tolerance alone (1e-6) within 0.3 of their standard errors (measured 0.17),
    in fewer iterations (6 against 10)."""
    data, guesses = lv_problem(0.01)
    problem = Problem(lv_system(TRUTH_ROW * 1.1), [data.t], [data.x[:, :1]], guesses)
    quick = problem.fit()
    tight = problem.fit(resolution=0.0)
    se = tight.standard_errors()
    change = np.abs(quick.system.free_values() - tight.system.free_values()) / se
    assert change.max() < 0.3
    assert quick.iterations < tight.iterations
    assert quick.data_cost - tight.data_cost < 2 * 0.05


def test_a_fit_tells_which_bounds_would_have_given_it_up_sooner():
    """A wrong structure (h' constant) on prey-only LV misses by about 10^4 noise
    variances; its give-up checks (from half of each pass's iterations, and between the
    passes) are recorded. A bound above all of them gives the same fit, to the bit; one
    below the first stops the fit there, and the record says so both ways; a bound
    given as a function is asked at every check."""
    data, guesses = lv_problem(0.01)
    problem = Problem(lv_system(np.array([0.0, A * G, 0.0, 0.0, 0.0])), [data.t],
                      [data.x[:, :1]], guesses)
    watch = GiveUpWatch()
    full = problem.fit(max_iterations=6, watch=watch)
    assert full.residual_variance > 1e3 and len(watch.went_on) >= 3
    assert watch.gave_up_at is None and watch.dof == problem.n_data - full.starts.size - 1
    high = 2.0 * max(watch.went_on) / watch.dof
    low = 0.5 * min(watch.went_on) / watch.dof
    assert watch.same_under(high) and watch.same_under(np.inf)
    assert not watch.same_under(low)
    same = problem.fit(max_iterations=6, give_up=high)
    assert same.iterations == full.iterations
    assert np.array_equal(same.system.coef, full.system.coef)
    assert np.array_equal(same.starts, full.starts)
    stopped_watch = GiveUpWatch()
    stopped = problem.fit(max_iterations=6, give_up=low, watch=stopped_watch)
    assert stopped.iterations == 3 and stopped.iterations < full.iterations  # 6 // 2
    assert stopped_watch.went_on == [] and stopped_watch.gave_up_at == watch.went_on[0]
    assert stopped_watch.same_under(low) and not stopped_watch.same_under(high)
    asked = []

    def falling():  # no bound at the first check, then the low one
        asked.append(None)
        return np.inf if len(asked) == 1 else low

    later = problem.fit(max_iterations=6, give_up=falling)
    # asked at iterations 3 (goes on) and 4 (gives up), then after the pass (stops)
    assert later.iterations == 4 and len(asked) == 3


def test_refinement_recovers_exact_coefficients():
    """Noise-free prey data, the true structure, hidden coefficients 20% off: the fit by
    integration returns them within 1e-4 (relative) and the segments join up."""
    data, guesses = lv_problem(0.0)
    problem = Problem(lv_system(TRUTH_ROW * 1.2), [data.t], [data.x[:, :1]], guesses)
    fit = problem.fit()
    np.testing.assert_allclose(fit.system.coef[1, :4], TRUTH_ROW[:4], rtol=1e-4)
    assert fit.gap < 0.05
    assert problem.joins(fit) and problem.jumps(fit).max() < 1e-3 * JOIN


def test_a_hidden_state_that_shrinks_and_jumps_does_not_join():
    """x' = 1e5 h, h' = 0 on data whose slope doubles halfway: with h set to each
    segment's slope / 1e5, the gaps are small on the guess's continuity scale (the
    check the penalty enforces), yet h jumps by twice its spread: not a trajectory.
    The same system with one constant h joins."""
    t = np.linspace(0.0, 10.0, 1000)
    slope = np.where(t < 5.0, 1.0, 2.0)
    x = np.where(t < 5.0, t, 5.0 + 2.0 * (t - 5.0))
    noisy = x + 0.01 * np.std(x) * np.random.default_rng(0).standard_normal(t.size)
    system = ParametricSystem(("x", "h"), 1, (H,), np.array([[1e5], [0.0]]),
                              np.array([[True], [False]]))
    problem = Problem(system, [t], [noisy[:, None]], [np.column_stack([x, slope])])
    t0 = problem.groups[0].starts

    def fit_with(h):
        x0 = np.concatenate([[0.0], np.cumsum(1e5 * h[:-1] * np.diff(t0))])  # joined
        starts = np.column_stack([x0, h])
        return Fit(system, starts, 0.0, 0.0, problem.n_data, problem._gap(system, starts),
                   0, np.zeros((1, 1)))

    jumping = fit_with(np.interp(t0, t, slope) / 1e5)
    assert jumping.gap < 1e-2  # the continuity penalty's own measure is satisfied
    assert not problem.joins(jumping) and problem.jumps(jumping)[0] > 1.0
    assert problem.joins(fit_with(np.full(t0.size, 1.5e-5)))
    # the same jumps by a state as large as its guess: the penalty itself sees them
    visible = dataclasses.replace(system, coef=np.array([[1.0], [0.0]]))
    problem = Problem(visible, [t], [noisy[:, None]], [np.column_stack([x, slope])])
    starts = jumping.starts * np.array([1.0, 1e5])
    assert problem._gap(visible, starts) > 10 and problem.joins(
        Fit(visible, starts, 0.0, 0.0, problem.n_data, 0.0, 0, np.zeros((1, 1))))


def test_a_move_or_fit_that_does_not_join_is_refused(monkeypatch):
    """Wired in: with every fit declared not joining, term selection makes no move and
    the judge leaves the system unscored ("does not join"); ranked without scores, such
    a system comes after one that blew up, whatever their sizes."""
    problem, candidates = swapped_lv_problem()
    fit = problem.fit()
    monkeypatch.setattr(Problem, "joins", lambda self, fit: False)
    assert select_terms(problem, fit, candidates)[1] == []
    verdict = finish(Trial(None, problem, fit, candidates, 1.0))
    assert not verdict.scored and verdict.history == ("does not join",)
    small = dataclasses.replace(verdict, history=("does not join",))
    large = _verdict(1.0, 0.0, 9, 1)
    large.scored, large.history = False, ("blew up",)
    large.cv = np.inf
    assert judge.rank([small, large])[0][0] is large


def test_multiple_shooting_converges_on_a_chaotic_system():
    """Lorenz over 20 time units (about 20 Lyapunov times) with every coefficient 10%
    off: single shooting has no useful gradient there; multiple shooting recovers the
    coefficients within 0.1% from noise-free data."""
    data = systems.lorenz(n_times=2000, t_end=20.0)
    feats = (X, Y, X * Z, X * Y, Z)
    truth = np.array([[-10.0, 10.0, 0, 0, 0], [28.0, -1.0, -1.0, 0, 0],
                      [0, 0, 0, 1.0, -8.0 / 3.0]])
    system = ParametricSystem(("x", "y", "z"), 3, feats, truth * 1.1, truth != 0)
    fit = Problem(system, [data.t], [data.x], [data.x]).fit()
    np.testing.assert_allclose(fit.system.coef[truth != 0], truth[truth != 0], rtol=1e-3)


def test_standard_errors_are_calibrated():
    """Six noise draws at 2%: the hidden-equation errors in units of their standard
    errors behave like standard normals (|z| < 3.5 everywhere, mean z^2 between 0.3
    and 3)."""
    z = []
    for seed in range(6):
        data, guesses = lv_problem(0.02, seed)
        fit = Problem(lv_system(TRUTH_ROW * 1.05), [data.t], [data.x[:, :1]], guesses).fit()
        z.append((fit.system.free_values() - TRUTH_ROW[:4]) / fit.standard_errors())
    z = np.concatenate(z)
    assert np.all(np.abs(z) < 3.5)
    assert 0.3 < np.mean(z**2) < 3.0


def test_state_std_covers_the_true_hidden_state():
    data, guesses = lv_problem(0.02)
    problem = Problem(lv_system(TRUTH_ROW), [data.t], [data.x[:, :1]], guesses)
    fit = problem.fit()
    hidden = problem.trajectories(fit)[0][:, 1]
    std = problem.state_std(fit)[0][:, 1]
    truth = A - B * data.x_clean[:, 1]
    assert np.all(std > 0)
    assert np.mean(np.abs(hidden - truth) <= 3 * std) > 0.9


def test_held_out_score_separates_right_and_wrong_structures():
    """At 1% noise the right hidden equation reproduces held-out segments down to the
    noise (score about 1); without its x h term it cannot (score > 10)."""
    data, guesses = lv_problem(0.01)
    right = Problem(lv_system(TRUTH_ROW), [data.t], [data.x[:, :1]], guesses)
    score, se, _ = cross_validate(right, right.fit())
    assert 0.8 < score < 1.3 and se < 0.2
    wrong_row = TRUTH_ROW.copy()
    wrong_row[0] = 0.0
    wrong = Problem(lv_system(wrong_row), [data.t], [data.x[:, :1]], guesses)
    assert cross_validate(wrong, wrong.fit())[0] > 10


def test_term_selection_finds_the_missing_term_and_drops_the_spurious_one():
    """Start without x h and with a spurious h x^2 (so the two trade places, a swap):
    the selection ends on the true four terms, coefficients within 1% at 1% noise."""
    problem, candidates = swapped_lv_problem()
    fit, history = select_terms(problem, problem.fit(), candidates)
    assert history
    assert list(np.flatnonzero(fit.system.free[1])) == [0, 1, 2, 3]
    np.testing.assert_allclose(fit.system.coef[1, :4], TRUTH_ROW[:4], rtol=0.01)


def test_blow_up_is_raised_not_hung():
    data, guesses = lv_problem(0.0)
    problem = Problem(lv_system(TRUTH_ROW), [data.t], [data.x[:, :1]], guesses)
    starts = problem.initial_starts.copy()
    starts[:, 1] = 1e6  # h enormous: x explodes immediately
    with pytest.raises(BlowUp):
        problem.equations(problem.system, starts, np.ones(problem.n_segments), 1.0)


def _verdict(cv, se, size, key, pivot=(0, 0), errors=None, stage_one=False):
    system = SimpleNamespace(state_names=("x", "h"), features=(key,),
                             free=np.ones((1, 1), bool), coef=np.ones((1, 1)))
    proposal = SimpleNamespace(structure=SimpleNamespace(pivots=(pivot,)), order=1, nested=(),
                               stage_one=stage_one)
    return SimpleNamespace(cv=cv, cv_se=se, size=size, system=system, scored=True,
                           proposal=proposal, errors=errors)


def _segments(mean, spread, shift, n=8, seed=0):
    """Held-out errors of ``n`` segments: a shared pattern (hard segments are hard for
    every system) of the given spread, plus a system's own ``shift``."""
    pattern = np.random.default_rng(seed).standard_normal(n)
    return mean + spread * (pattern - pattern.mean()) + shift


def test_paired_evidence_reads_differences_on_the_same_segments():
    """Scores 0.06 apart with standard errors of 0.035 (the segments vary together):
    pairing resolves a consistent difference, and does not resolve one that changes
    sign; with 4 segments the t quantile (3.18) asks for more than with 40 (2.02)."""
    base = _segments(1.0, 0.1, 0.0)
    better = _verdict(0.94, 0.035, 7, 1, errors=base - 0.06 + 0.002 * np.arange(8))
    worse = _verdict(1.0, 0.035, 5, 2, errors=base)
    assert paired_evidence(better, worse) and not paired_evidence(worse, better)
    mixed = _verdict(0.94, 0.035, 7, 1, errors=base - 0.06 + 0.3 * (-1.0) ** np.arange(8))
    assert not paired_evidence(mixed, worse)
    d = np.array([0.1, 0.1, 0.1, 0.1]) + np.array([-0.05, 0.05, -0.04, 0.04])  # t = 3.8
    few = _verdict(0.0, 0.0, 5, 1, errors=np.zeros(4))
    assert paired_evidence(few, _verdict(0.0, 0.0, 5, 1, errors=d))
    d = d - 0.06  # mean 0.04, t = 1.5: below 3.18 with 3 degrees of freedom
    assert not paired_evidence(few, _verdict(0.0, 0.0, 5, 1, errors=d))
    assert paired_evidence(few, _verdict(0.0, 0.0, 5, 1)) is False  # unpaired: no evidence
    assert paired_evidence(few, _verdict(0.0, 0.0, 5, 1), unpaired=True)


def test_hidden_initial_values_count_once_per_recording():
    """A hidden state adds one initial value per recording to a system's size: over 4
    recordings, a law in one hidden state with 4 coefficients (8 parameters) is smaller
    than one in two hidden states with 3 (11), and ranking prefers it at the same
    score; over one recording the second (5 against 5) would tie on size."""
    def verdict(n_hidden, n_free, recordings, pivot):
        names = ("x",) + tuple(f"h{a}" for a in range(n_hidden))
        free = np.zeros((len(names), 3), dtype=bool)
        free.flat[:n_free] = True
        system = ParametricSystem(names, 1, ("1", "x", "h0"), np.zeros(free.shape), free)
        proposal = SimpleNamespace(structure=SimpleNamespace(pivots=(pivot,)), order=1,
                                   nested=(), stage_one=False)
        return Verdict(proposal, SimpleNamespace(system=system),
                       SimpleNamespace(groups=[None] * recordings), 1.0, 0.05, (), 1.0,
                       errors=np.ones(8))
    one, two = verdict(1, 4, 4, (0, 0)), verdict(2, 3, 4, (0, 1))
    assert (one.size, two.size) == (8, 11)
    assert verdict(1, 4, 1, (0, 0)).size == verdict(2, 3, 1, (0, 1)).size == 5
    assert rank([two, one])[0][0] is one


def test_a_larger_alternative_vetoes_confidence_only_when_favoured():
    """An alternative with another hidden state and more parameters, scoring as well on
    the same segments, leaves the chosen system confident; one that the held-out data
    favour (lower error on every segment) makes it uncertain. A sparser system outside
    the one-standard-error band that the paired errors do not reject is chosen (prey-only
    LV at 12 samples per cycle: the exact law, 5 parameters, 0.057 +- 0.025 above a
    7-parameter approximation over 7 segments)."""
    base = _segments(1.0, 0.2, 0.0)
    small = _verdict(1.0, 0.07, 5, 1, errors=base)
    same = _verdict(1.0, 0.07, 7, 2, pivot=(0, 1), errors=base + 0.01 * (-1.0) ** np.arange(8))
    ordered, uncertain = rank([small, same])
    assert ordered[0] is small and uncertain == []
    favoured = _verdict(0.96, 0.07, 7, 2, pivot=(0, 1), errors=base - 0.04)
    ordered, uncertain = rank([small, favoured])
    assert ordered[0] is small and uncertain == [favoured]
    exact = _verdict(0.23, 0.05, 5, 1, errors=np.array([0.50, 0.13, 0.14, 0.17, 0.20,
                                                          0.22, 0.26]))
    approx = _verdict(0.17, 0.03, 7, 2, pivot=(0, 1),
                      errors=np.array([0.34, 0.18, 0.07, 0.10, 0.20, 0.13, 0.20]))
    assert exact.cv > approx.cv + approx.cv_se  # outside the band
    ordered, uncertain = rank([exact, approx])
    assert ordered[0] is exact and uncertain == []


def test_stage_one_law_scoring_no_worse_than_a_sparser_choice_makes_it_uncertain():
    """Stage one's own law, larger than the chosen one (5 against 3 parameters) and not
    it with terms added, scoring no worse with its paired errors lower by 1.25
    standard errors (the competition case: 0.004 +- 0.003 over 40 segments), makes the
    result uncertain. Not when it is the chosen law with a term added, nor when the
    paired errors do not lean towards it (0.25 standard errors), nor when its score is
    worse, nor when the leaning law is another larger one (not stage one's), nor where
    both scores are ties at the noise-free floor (below ``TIE``)."""
    base = _segments(1.0, 0.2, 0.0, n=40)
    noise = np.random.default_rng(1).standard_normal(40)
    noise = (noise - noise.mean()) / noise.std(ddof=1) * np.sqrt(40) * 0.0032
    chosen = _verdict(0.9746, 0.027, 3, 1, pivot=(0, 1), errors=base)
    leaning = _verdict(0.9706, 0.028, 5, 2, errors=base - 0.004 + noise, stage_one=True)
    ordered, uncertain = rank([chosen, leaning])
    assert ordered[0] is chosen and uncertain == [leaning]
    other = _verdict(0.9706, 0.028, 5, 2, errors=base - 0.004 + noise)
    assert rank([chosen, other]) == ([chosen, other], [])
    # the same hidden state (pivot) with other terms: not nested, so a rival
    same_state = _verdict(0.9706, 0.028, 5, 2, pivot=(0, 1), errors=base - 0.004 + noise,
                          stage_one=True)
    assert rank([chosen, same_state]) == ([chosen, same_state], [same_state])
    more = _verdict(0.9706, 0.028, 5, 1, pivot=(0, 1), errors=base - 0.004 + noise,
                    stage_one=True)
    more.system = SimpleNamespace(state_names=("x", "h"), features=(1, 2),
                                  free=np.ones((1, 2), bool), coef=np.ones((1, 2)))
    assert rank([chosen, more]) == ([chosen, more], [])
    weak = _verdict(0.9738, 0.028, 5, 2, errors=base - 0.0008 + noise, stage_one=True)
    assert rank([chosen, weak]) == ([chosen, weak], [])
    worse = _verdict(0.9750, 0.028, 5, 2, errors=base + 0.0004 + noise, stage_one=True)
    assert rank([chosen, worse]) == ([chosen, worse], [])
    # noise-free data: scores far below TIE are ties, a lean among them is rounding
    exact = _verdict(9.2e-6, 1.5e-6, 3, 1, pivot=(0, 1), errors=1e-5 * base)
    rounding = _verdict(8.4e-6, 1.5e-6, 5, 2, errors=1e-5 * (base - 0.004 + noise),
                        stage_one=True)
    assert rank([exact, rounding]) == ([exact, rounding], [])


def test_rank_prefers_the_smallest_within_one_standard_error():
    """One-standard-error rule: the 5-term system within the best one's band wins over
    the better-scoring 7-term one with the same hidden state (parsimony, not
    uncertainty); a system whose hidden state is another coefficient, inside the band,
    makes the result uncertain whatever its size; one outside the band does not, nor
    one that only adds a hidden state to the chosen one's."""
    best = _verdict(1.00, 0.05, 7, 1)
    small = _verdict(1.04, 0.05, 5, 2)
    far = _verdict(1.20, 0.05, 5, 4, pivot=(0, 1))
    ordered, uncertain = rank([best, small, far])
    assert ordered[0] is small and uncertain == []
    other = _verdict(1.03, 0.04, 6, 3, pivot=(0, 2))
    more = _verdict(1.02, 0.04, 8, 5)
    more.proposal.structure.pivots = ((0, 0), (1, 1))
    ordered, uncertain = rank([best, small, other, far, more])
    assert ordered[0] is small and uncertain == [other]


def test_doubts_name_each_failed_check():
    """A refined system is doubted when its held-out score is above the noise by more
    than the slack (two standard errors), when refinement hit its iteration limit, and
    for each hidden-equation coefficient within two standard errors of zero, and when
    its segments end a noise level or more from the next one's start; a system that
    passes all four has no doubts."""
    ok = Refinement(0.1, 0.05, 0.0, 10, 5, "converged")
    h = sp.Symbol("h", real=True)
    terms = (Term("h", h, -1.5, 0.01, False), Term("x", h, 1.0, math.nan, True))
    assert doubts(1.05, 0.03, ok, terms, ["h"]) == ()
    assert doubts(1.2, 0.05, ok, terms, ["h"]) == ()  # within two standard errors
    high = doubts(1.5, 0.05, ok, terms, ["h"])
    assert len(high) == 1 and "does not reproduce held-out data" in high[0]
    stopped = dataclasses.replace(ok, status="iteration_limit")
    assert "iteration limit" in doubts(1.0, 0.03, stopped, terms, ["h"])[0]
    weak = terms + (Term("h", h**2, 0.02, 0.015, False),)
    found = doubts(1.0, 0.03, ok, weak, ["h"])
    assert len(found) == 1 and "1 hidden-equation coefficient(s)" in found[0]
    assert "dh/dt: h**2" in found[0]
    torn = dataclasses.replace(ok, continuity_gap=1.5)  # segments 1.5 noise levels apart
    found = doubts(1.0, 0.03, torn, terms, ["h"])
    assert [d.kind for d in found] == ["not continuous"] and "1.5 noise levels" in found[0]
    near = dataclasses.replace(ok, continuity_gap=0.9)
    assert doubts(1.0, 0.03, near, terms, ["h"]) == ()


def test_ambiguities_report_a_term_the_data_cannot_tell_from_another():
    """x and a near-copy of it, x (1 + 1e-4 x), cannot be told apart in the hidden
    equation: swapping one for the other changes the misfit by less than AMBIGUITY.
    The true terms against the library's other terms (h x^2) are told apart."""
    data, guesses = lv_problem(0.01)
    features = LV_FEATURES + (X * (1 + 1e-4 * X),)
    coef = np.zeros((2, 6))
    coef[0, 0] = 1.0
    coef[1, :5] = TRUTH_ROW
    free = np.zeros((2, 6), dtype=bool)
    free[1, :4] = True
    problem = Problem(ParametricSystem(("x", "h"), 1, features, coef, free), [data.t],
                      [data.x[:, :1]], guesses)
    fit = problem.fit()
    candidates = np.zeros_like(free)
    candidates[1, 4:] = True
    found = ambiguities(problem, fit, candidates)
    assert [move for move, _ in found] == [("swap", ((1, 3), (1, 5)))]
    assert abs(found[0][1]) < AMBIGUITY
    candidates[1, 5] = False
    assert ambiguities(problem, fit, candidates) == []


def _exact_lv_fit():
    """The LV problem at 1% noise with the exact hidden law's four terms free: the
    problem, its fit and the free cells."""
    data, guesses = lv_problem(0.01)
    coef = np.zeros((2, 5))
    coef[0, 0] = 1.0
    coef[1] = TRUTH_ROW
    free = np.zeros((2, 5), dtype=bool)
    free[1, :4] = True
    problem = Problem(ParametricSystem(("x", "h"), 1, LV_FEATURES, coef, free), [data.t],
                      [data.x[:, :1]], guesses)
    return problem, problem.fit(), free


def test_weak_terms_fail_safe():
    """The exact LV hidden law: every term strongly supported (no weak term). A refit
    that fails is not a pass: each term whose removal is predicted cheap enough to need
    a refit comes back with change NaN; a refit that blows up says the term is needed."""
    problem, fit, free = _exact_lv_fit()
    candidates = np.zeros_like(free)
    candidates[1, 4] = True
    assert weak_terms(problem, fit, candidates) == []
    # a bar so high that every drop is predicted under it: each one is refitted
    original = terms_module.EVIDENCE
    try:
        terms_module.EVIDENCE = 1e12
        checked = weak_terms(problem, fit, candidates)
        assert len(checked) == 4 and all(np.isfinite(c) for _, c, _ in checked)

        def fails(*args):
            raise np.linalg.LinAlgError("singular")

        def blows(*args):
            raise BlowUp("left the bounded region")

        terms_module._exact_refit, saved = fails, terms_module._exact_refit
        try:
            failed = weak_terms(problem, fit, candidates)
            assert len(failed) == 4
            assert all(np.isnan(c) for _, c, _ in failed[:3])  # refitted: failed
            assert np.isfinite(failed[3][1])  # beyond the refit limit: predicted change
            terms_module._exact_refit = blows
            blown = weak_terms(problem, fit, candidates)
            assert len(blown) == 1 and blown[0][0] == failed[3][0]  # only the unrefitted
        finally:
            terms_module._exact_refit = saved
    finally:
        terms_module.EVIDENCE = original


def test_a_refit_that_cannot_count_gives_up():
    """Dropping a term of the exact LV hidden law: no refit gets back to the fit's own
    misfit. Asked to reach it, a refit still ``HOPELESS`` times above it gives up after
    its first pass (``h``: 4 iterations, not 8) or at half its iterations (``x``: 20 of
    40, where the full refit crawls to its limit): fewer iterations, the same verdict
    (above the line either way). Against the full refit's own final misfit, a line it
    never goes fifty times above, the refit is the full one, to the bit (a bound off in
    scale, by the degrees of freedom say, would stop it)."""
    problem, fit, free = _exact_lv_fit()
    model = terms_module.Quadratic(problem, fit, np.zeros_like(free))
    drops = {move[1]: keep for _, move, keep in model.moves(0.0, 1.0) if move[0] == "drop"}
    for cell in [(1, 2), (1, 3)]:  # h, x
        full = terms_module._exact_refit(problem, fit, model, drops[cell])
        bounded = terms_module._exact_refit(problem, fit, model, drops[cell],
                                            lambda _: fit.data_cost)
        assert full.data_cost > fit.data_cost
        assert bounded.iterations < full.iterations
        assert bounded.data_cost > HOPELESS * fit.data_cost
        final = full.data_cost
        never = terms_module._exact_refit(problem, fit, model, drops[cell],
                                          lambda _, final=final: final)
        assert never.data_cost == full.data_cost and never.iterations == full.iterations
        assert np.array_equal(never.system.coef, full.system.coef)


def test_weak_term_sentences_say_what_was_not_checked():
    system = ParametricSystem(("x", "h"), 1, LV_FEATURES, np.zeros((2, 5)),
                              np.zeros((2, 5), dtype=bool))
    found = [((1, 1), 3.0, 20.0), ((1, 2), math.nan, 20.0), (None, math.nan, math.nan)]
    weak, failed, blown = weak_doubts(found, system, {}, {})
    assert "support 1 in dh/dt only weakly (dropping it raises the misfit by 3" in weak
    assert "support of h in dh/dt could not be checked (refitting without it failed)" in failed
    assert "could not be checked (refitting without a term blew up)" in blown


def test_a_constant_hidden_state_that_differs_between_segments_is_a_doubt():
    """dr/dt = 0 makes r one parameter per segment: the segments then do not share one
    law. Equal constants (within two standard errors), or one segment, pass."""
    h = sp.Symbol("r", real=True)
    terms = (Term("x", h, 1.0, math.nan, True),)  # r carries x; dr/dt = 0

    def segments(values, error=0.01):
        trs = [np.column_stack([np.zeros(5), np.full(5, v)]) for v in values]
        return trs, [np.full((5, 2), error) for _ in values]

    assert segment_constant_doubts(terms, ["r"], 1, *segments([0.5, 0.8, 1.1])) != ()
    found = segment_constant_doubts(terms, ["r"], 1, *segments([0.5, 0.8, 1.1]))[0]
    assert "r has no dynamics of its own but takes different constant values" in found
    assert "0.5, 0.8, 1.1" in found
    assert segment_constant_doubts(terms, ["r"], 1, *segments([0.5, 0.51, 0.5])) == ()
    assert segment_constant_doubts(terms, ["r"], 1, *segments([0.5])) == ()
    moving = terms + (Term("r", h, -0.3, 0.01, False),)
    assert segment_constant_doubts(moving, ["r"], 1, *segments([0.5, 0.8])) == ()
    (blown,) = segment_constant_doubts(terms, ["r"], 1, *segments([0.5, np.nan, 0.5]))
    assert "its constant could not be read in every recording" in blown


def _lv_with_small_term(eps, noise=0.01, n_times=1500):
    """x' = x h, h' = the LV hidden law + eps h x^2 (x seen with ``noise``), and the
    problem of fitting the LV law without h x^2 (the candidate that may be added)."""
    row = TRUTH_ROW.copy()
    row[4] = eps
    t = np.linspace(0.0, 15.0, n_times)
    states = solve_ivp(lambda _, s: [s[0] * s[1], row @ [s[0] * s[1], 1.0, s[1], s[0],
                                                         s[1] * s[0] ** 2]],
                       (0.0, 15.0), [10.0, A - B * 5.0], t_eval=t, rtol=1e-10,
                       atol=1e-10).y.T
    observed = states[:, :1] + noise * states[:, 0].std() * \
        np.random.default_rng(0).standard_normal((n_times, 1))
    problem = Problem(lv_system(TRUTH_ROW), [t], [observed], [states])
    candidates = np.zeros((2, 5), dtype=bool)
    candidates[1, 4] = True
    return problem, problem.fit(), candidates


def test_missing_terms_name_a_term_the_data_call_for():
    """Fitted without h x^2: where the law has none, h x^2 is not called for (its
    addition misses the criterion by more than the margin); where the law has
    1e-4 h x^2, adding it lowers the misfit by far more than a term costs: named, with
    its exact change. The margin decides: raised above the shortfall, the absent term
    is named too. A refit that fails does not count (the fit without the term stands)."""
    problem, fit, candidates = _lv_with_small_term(0.0)
    assert missing_terms(problem, fit, candidates) == []
    strong = _lv_with_small_term(1e-4)
    (cell, change, price), = missing_terms(*strong)
    assert cell == (1, 4) and change < -10 * price
    added = strong[0].fit(lv_system(TRUTH_ROW + [0, 0, 0, 0, 1e-4],
                                    free_row=np.ones(5, dtype=bool)))
    assert change == pytest.approx((added.data_cost - strong[1].data_cost)
                                   / max(strong[1].residual_variance, 1.0), rel=0.02)
    model = terms_module.Quadratic(problem, fit, candidates)
    (gain, _, _), = model.additions(terms_module._price(problem, fit, candidates),
                                    max(fit.residual_variance, 1.0))
    assert -gain > terms_module.MARGIN  # the absent term's predicted shortfall
    original = terms_module.MARGIN
    try:
        terms_module.MARGIN = -gain + 1.0
        (cell, change, price), = missing_terms(problem, fit, candidates)
        assert cell == (1, 4) and change < 0 and change + price < terms_module.MARGIN

        def fails(*args):
            raise np.linalg.LinAlgError("singular")

        terms_module._exact_refit, saved = fails, terms_module._exact_refit
        try:
            assert missing_terms(problem, fit, candidates) == []
        finally:
            terms_module._exact_refit = saved
    finally:
        terms_module.MARGIN = original


def test_missing_term_sentences():
    system = ParametricSystem(("x", "h"), 1, LV_FEATURES, np.zeros((2, 5)),
                              np.zeros((2, 5), dtype=bool))
    nearly, needed = missing_doubts([((1, 1), -10.1, 11.7), ((1, 3), -40.0, 11.7)], system, {}, {})
    assert ("1 in dh/dt was left out, but the data nearly call for it (adding it lowers "
            "the misfit by 10.1 residual variances, within 2 of the 11.7") in nearly
    assert "x in dh/dt was left out, but the data call for it" in needed
    five = [((1, c), -10.0, 11.0) for c in range(5)]
    assert missing_doubts(five, system, {}, {})[-1].startswith("2 more left-out terms")


def test_ar1_noise_is_read_and_whitened():
    """AR(1) noise of correlation 0.8 between samples (3% of the prey's std): read as
    such (correlation within 0.1, level within 25%), and the true system's misfit per
    degree of freedom, whitened, is about 1 (0.7-1.4). Read as white, the same noise's
    level comes out about 3 times too low (and the misfit 9 times too high)."""
    data, guesses = lv_problem(0.0, n_times=2000)
    rng = np.random.default_rng(5)
    e = np.zeros(len(data.t))
    for k in range(1, len(e)):
        e[k] = 0.8 * e[k - 1] + np.sqrt(1 - 0.64) * rng.standard_normal()
    sigma = 0.03 * data.x[:, 0].std()
    x = data.x[:, :1] + sigma * e[:, None]
    level, phi = ar1_noise(x, data.t)
    assert abs(phi[0] - 0.8) < 0.1 and abs(level[0] / sigma - 1) < 0.25
    assert noise_level(x, data.t)[0] < 0.45 * sigma
    problem = Problem(lv_system(TRUTH_ROW), [data.t], [x], guesses)
    assert problem.carry is not None
    fit = problem.fit(max_iterations=20)
    assert 0.7 < fit.residual_variance < 1.4


def test_white_noise_is_not_read_as_coloured():
    data, _ = lv_problem(0.02, n_times=2000)
    level, phi = ar1_noise(data.x[:, :1], data.t)
    assert phi[0] == 0.0 and level[0] is None


def test_hermite_interpolation_in_place_is_the_plain_sum_to_the_bit():
    """The numpy path interpolates in place; the same products summed left to right as
    the plain expression (the torch path's), digit for digit, and twice in a row (the
    table made at the first call is reused, not consumed)."""
    from latentsindy._stage_two.fit.shooting import _hermite, make_groups

    t = np.linspace(0.0, 3.0, 301)
    group = make_groups([t], [np.zeros((301, 1))], 0.5, 0.03)[0]
    rng = np.random.default_rng(4)
    shape = (group.n_segments, len(group.grid), 2, 5)
    z, dz = rng.normal(size=shape), rng.normal(size=shape)
    for _ in range(2):
        got = _hermite(z, dz, group)
        rows, nxt, w00, w10, w01, w11 = (np.asarray(a) for a in group.hermite["numpy"])
        flat, dflat = z.reshape(-1, 2, 5), dz.reshape(-1, 2, 5)
        w = [a[:, None, None] for a in (w00, w10, w01, w11)]
        plain = w[0] * flat[rows] + w[1] * dflat[rows] + w[2] * flat[nxt] + w[3] * dflat[nxt]
        np.testing.assert_array_equal(got, plain.reshape(got.shape))
        assert np.array_equal(nxt, rows + 1)
