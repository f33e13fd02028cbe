"""The varying-coefficient model behind stage one's structure choice and band: exact
linear algebra against dense references, and recovery of known coefficients."""

import numpy as np
import pytest
from scipy.linalg import cholesky_banded
from scipy.special import gammaln

from latentsindy._core.derivatives import choose_window
from latentsindy._stage_one import vcm
from latentsindy._stage_one.evidence import MAX_KNOTS, VaryingCoefficients, resolution
from latentsindy._stage_one.vcm import LevelGram, spline_basis
from latentsindy._stage_one.vcm_fit import EquationModel, _Normal
from latentsindy._stage_one.vcm_spread import selected_inverse


def test_spline_basis_is_a_partition_of_unity():
    t = np.sort(np.random.default_rng(0).uniform(0, 3, 500))
    first, values = spline_basis(t, 20, (0.0, 3.0))
    np.testing.assert_allclose(values.sum(axis=1), 1.0, atol=1e-12)
    assert first.min() >= 0 and first.max() <= 16


def _band_of(a, w):
    n = len(a)
    band = np.zeros((w + 1, n))
    for off in range(min(w, n - 1) + 1):
        band[w - off, off:] = np.diag(a, off)
    return band


@pytest.mark.parametrize("n, w", [(40, 5), (41, 3), (33, 16), (70, 20), (41, 0), (3, 5),
                                  (1, 2), (16, 4), (17, 4), (100, 1), (61, 15)])
def test_selected_inverse_matches_the_dense_inverse(n, w):
    """Blocks of 16 rows and of w (w >= 16), a last block cut short or whole, a band
    wider than the matrix and a diagonal one; NaN in the factor's unused corner (outside
    the matrix) changes nothing."""
    rng = np.random.default_rng(0)
    mask = np.abs(np.subtract.outer(np.arange(n), np.arange(n))) <= w
    b = rng.normal(size=(n, n))
    a = (b + b.T) * mask
    a += np.eye(n) * (np.abs(a).sum(axis=1).max() + 1)
    u = cholesky_banded(_band_of(a, w))
    inv = selected_inverse(u)
    dense = np.linalg.inv(a)
    for off in range(min(w, n - 1) + 1):
        np.testing.assert_allclose(inv[w - off, off:], np.diag(dense, off), atol=1e-14)
    for off in range(1, w + 1):
        u[w - off, :off] = np.nan
    np.testing.assert_array_equal(selected_inverse(u), inv)


def test_selected_inverse_is_accurate_on_an_ill_conditioned_band():
    """A = U'U with U's diagonal spanning eight decades (condition ~1e16, the range of
    stage one's roughness): every entry inside the band within 1e-9 of sqrt(S_ii S_jj)
    of the inverse from dense triangular solves with the same U."""
    from scipy.linalg import solve_triangular

    rng = np.random.default_rng(3)
    n, w = 120, 12
    u_dense = np.triu(rng.normal(size=(n, n)) * 0.3) * (np.subtract.outer(
        np.arange(n), np.arange(n)) >= -w)
    np.fill_diagonal(u_dense, np.logspace(-4, 4, n)[rng.permutation(n)])
    u = _band_of(u_dense, w)  # reads the upper diagonals only
    u_inv = solve_triangular(u_dense, np.eye(n))
    dense = u_inv @ u_inv.T
    inv = selected_inverse(u)
    scale = np.sqrt(np.diag(dense))
    for off in range(w + 1):
        err = np.abs(inv[w - off, off:] - np.diag(dense, off)) / (scale[:n - off] * scale[off:])
        assert err.max() < 1e-9, (off, err.max())


def _small_problem():
    rng = np.random.default_rng(1)
    n, m = 400, 12
    t = np.sort(rng.uniform(0, 10, n))
    x = np.cumsum(rng.normal(size=(n, 2)), axis=0) * 0.1
    theta = np.column_stack([np.ones(n), x[:, 0], x[:, 1]])
    gram = LevelGram([x], [t], [theta], m, (t[0], t[-1]), 25).equation(0)
    return t, gram, m


def test_banded_evidence_equals_the_dense_formula():
    t, g, m = _small_problem()
    model = EquationModel(g, 0.01)
    varying, constant = (1, 2), (0,)
    log_rough = np.array([2.0, 4.0])
    value, _ = model._solve(_Normal(g, varying, constant), log_rough, [None, None])
    size, v = 2 * m + 1, 2
    gram = np.zeros((size, size))
    for d in range(g.reach):
        for k in range(m - d):
            for a in range(v):
                for b in range(v):
                    i, j = k * v + a, (k + d) * v + b
                    gram[i, j] = gram[j, i] = g.band[d][k, varying[a], varying[b]]
    gram[:-1, -1] = gram[-1, :-1] = g.spline_const[:, varying, 0].reshape(-1)
    gram[-1, -1] = g.const[0, 0]
    rhs = np.concatenate([g.spline_y[:, varying].reshape(-1), [g.const_y[0]]])
    d2 = np.diff(np.eye(m), 2, axis=0)
    prior = np.zeros((size, size))
    for a in range(v):
        idx = np.arange(m) * v + a
        prior[np.ix_(idx, idx)] = np.exp(log_rough[a]) * d2.T @ d2 + model.ridge * np.eye(m)
    prior[-1, -1] = model.level
    resid = g.yy - rhs @ np.linalg.solve(gram + prior, rhs)
    dense = (gammaln(g.n / 2) - g.n / 2 * np.log(np.pi) + 0.5 * np.linalg.slogdet(prior)[1]
             - 0.5 * np.linalg.slogdet(gram + prior)[1] - g.n / 2 * np.log(resid))
    assert value == pytest.approx(dense, rel=1e-9)  # eigenvalue route for the prior


def test_adaptive_priors_kept_by_roughness_give_the_same_evidence_and_the_dense_log_det():
    """With per-knot weights: the log-determinant of each varying term's prior
    (ridge I + rough D2' Q D2) against the dense one, and :meth:`_solve` with the
    priors kept by (term, roughness) the same to the bit as computing each anew, one
    entry kept per term and roughness asked for."""
    t, g, m = _small_problem()
    model = EquationModel(g, 0.01)
    st = _Normal(g, (1, 2), (0,))
    rng = np.random.default_rng(5)
    weights = [rng.uniform(0.2, 3.0, m - 2), rng.uniform(0.2, 3.0, m - 2)]
    d2 = np.diff(np.eye(m), 2, axis=0)
    for q in weights:
        for rough in (1e-3, 7.0, 2e4):
            dense = np.linalg.slogdet(model.ridge * np.eye(m) + rough * d2.T @ (q[:, None] * d2))
            assert dense[0] == 1
            # the dense matrix is ill-conditioned (ridge ~1e-6 beside rough D2' Q D2)
            assert model._prior_logdet(q, rough) == pytest.approx(dense[1], rel=1e-8)
    known = {}
    for log_rough in ([4.0, 4.0], [2.0, 4.0], [2.0, 5.0], [2.0, 4.0], [3.0, 4.0]):
        kept = model._solve(st, np.array(log_rough), weights, known=known)
        anew = model._solve(st, np.array(log_rough), weights)
        assert kept[0] == anew[0]
        for a, b in zip(kept[1], anew[1], strict=True):
            np.testing.assert_array_equal(a, b)
    assert sorted(known) == [(0, np.exp(2.0)), (0, np.exp(3.0)), (0, np.exp(4.0)),
                             (1, np.exp(4.0)), (1, np.exp(5.0))]


def test_an_adaptive_fit_with_kept_priors_is_the_fit_computing_each_anew(monkeypatch):
    """The kept priors hold only while the weights are fixed: an adaptive fit (five
    variational steps, each with new weights) is the same to the bit as one that
    computes every prior anew. Kept across the steps, or used after the last update,
    they would change its score by up to hundreds of nats."""
    _, g, _ = _small_problem()
    kept = EquationModel(g, 0.01).fit((0, 1, 2), (1, 2), adaptive=True)
    monkeypatch.setattr(EquationModel, "_known_prior_logdet",
                        lambda self, a, q, rough, known: self._prior_logdet(q, rough))
    anew = EquationModel(g, 0.01).fit((0, 1, 2), (1, 2), adaptive=True)
    assert np.isfinite(kept.score) and kept.score == anew.score
    np.testing.assert_array_equal(kept.log_rough, anew.log_rough)
    np.testing.assert_array_equal(kept.spline, anew.spline)


def _varying_oscillator(noise, n=1500, seed=0):
    """xdot = a(t) y, ydot = -x with a(t) = 1 + 0.5 sin(0.2 t): the exact solution on a
    fine grid (RK4), sampled with noise every 40 fine steps."""
    a = lambda s: 1.0 + 0.5 * np.sin(0.2 * s)  # noqa: E731
    fine = np.linspace(0, 40, 40 * n)
    h = fine[1] - fine[0]
    f = lambda s, z: np.array([a(s) * z[1], -z[0]])  # noqa: E731
    z, out = np.array([1.0, 0.0]), [np.array([1.0, 0.0])]
    for s in fine[:-1]:
        k1 = f(s, z)
        k2 = f(s + h / 2, z + h / 2 * k1)
        k3 = f(s + h / 2, z + h / 2 * k2)
        k4 = f(s + h, z + h * k3)
        z = z + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        out.append(z)
    t, x = fine[::40], np.array(out)[::40]
    rng = np.random.default_rng(seed)
    return t, x + noise * x.std(axis=0) * rng.standard_normal(x.shape), a(t)


def test_a_varying_coefficient_is_recovered_and_its_band_covers_it():
    t, x, truth = _varying_oscillator(0.01)
    theta = np.column_stack([np.ones(len(t)), x])  # library 1, x, y
    scale = np.sqrt(np.mean(np.gradient(x, t, axis=0) ** 2, axis=0))
    vc = VaryingCoefficients([x], [t], [theta], scale, 0.01 * x.std(axis=0))
    choice = vc.choose(np.ones((2, 3), bool), np.ones((2, 3), bool), np.ones(2, bool),
                       np.ones((2, 3), bool), 0.05)
    assert (choice[0].fit.support, choice[0].fit.varying) == ((2,), (2,))
    assert (choice[1].fit.support, choice[1].fit.varying) == ((1,), ())
    mean, sd = choice[0].fit.series(*vc.basis)
    estimate = mean[:, 0] * scale[0]  # the feature "y" is unscaled here
    sd = sd[:, 0] * scale[0]
    assert np.sqrt(np.mean((estimate - truth) ** 2)) < 0.01  # 2% of its range
    assert np.mean(np.abs(estimate - truth) <= 2 * sd) > 0.85
    assert choice[1].fit.constants[0] * scale[1] == pytest.approx(-1.0, abs=0.005)


def test_resolution_follows_the_noise():
    t, clean, _ = _varying_oscillator(0.0)
    _, noisy, _ = _varying_oscillator(0.05)
    assert resolution(clean, t)[0] > resolution(noisy, t)[0]


def test_integration_windows_stay_short_where_the_knots_are_capped():
    """A series long enough to cap the knots (MAX_KNOTS): the windows stay two
    differentiator windows long instead of growing with the knot spacing (which
    integrated the library's noise over thousands of samples on 10^6 Lorenz samples)."""
    t = np.linspace(0.0, 4000.0, 200_000)
    x = np.column_stack([np.sin(t), np.cos(1.3 * t)])
    x += 0.01 * np.random.default_rng(0).standard_normal(x.shape)
    n_knots, window = resolution(x, t)
    differentiator = min(choose_window(x[:, j], t=t) for j in range(2))
    assert n_knots == MAX_KNOTS and (len(t) - 1) / (n_knots - 3) > differentiator
    assert window == max(4, round(2 * differentiator))


def test_normal_equations_do_not_depend_on_the_block_size(monkeypatch):
    """The normal equations are accumulated in blocks of windows (bounded memory):
    blocks of one window give the same matrices as one block."""
    t, x = np.linspace(0, 10, 300), np.random.default_rng(2).normal(size=(300, 2))
    theta = np.column_stack([np.ones(300), x])
    whole = LevelGram([x], [t], [theta], 20, (0.0, 10.0), 12)
    monkeypatch.setattr(vcm, "_BLOCK", 1)
    pieces = LevelGram([x], [t], [theta], 20, (0.0, 10.0), 12)
    for name in ("band", "spline_const", "spline_y", "const", "const_y", "yy"):
        np.testing.assert_allclose(getattr(pieces, name), getattr(whole, name), rtol=1e-12,
                                   atol=1e-12)
    assert pieces.n == whole.n


def test_a_hidden_state_is_not_split_into_state_functions():
    """Prey-only Lotka-Volterra, 8000 samples: xdot = h(t) x. Moving part of h into x^2
    and x^3 constants makes h a little smoother, which the evidence rewards (27 nats);
    such constants, which the generator did not propose, must earn their place by
    halving the variation's degrees of freedom or cutting the misfit, and do not."""
    from latentsindy import systems
    from latentsindy._core.derivatives import noise_level
    from latentsindy._core.differentiation import differentiate

    data = systems.lotka_volterra(t_end=80.0, n_times=8000, noise=0.01)
    x, t = data.x[:, :1], data.t
    theta = np.column_stack([x[:, 0], x[:, 0] ** 2, x[:, 0] ** 3])
    xdot = differentiate(None, [x], [t])[0][0]
    scale = np.sqrt(np.mean(theta**2, axis=0))
    vc = VaryingCoefficients([x], [t], [theta / scale], np.sqrt(np.mean(xdot**2, axis=0)),
                             noise_level([x], [t]))
    proposal = np.array([[True, False, False]])
    (choice,) = vc.choose(proposal, proposal, np.ones(1, bool), np.ones((1, 3), bool), 0.05)
    assert (choice.fit.support, choice.fit.varying) == ((0,), (0,))
    assert choice.rivals == ()


def test_random_sample_times_leave_no_quadrature_misfit():
    """Sorted uniformly random times (as the conditions benchmark draws them): the constant equation
    ydot = -x leaves the measurement noise, not more (the trapezoid rule's end
    correction, whose slopes come from those tiny steps, left 18 times the noise
    variance on the conditions benchmark's random times before it was restricted to
    uniform grids); on the uniform grid the same holds with the correction."""
    from scipy.integrate import solve_ivp

    rng = np.random.default_rng(0)
    for random_times in (False, True):
        t = (np.concatenate([[0.0], np.sort(rng.uniform(0, 40, 1498)), [40.0]])
             if random_times else np.linspace(0, 40, 1500))
        sol = solve_ivp(lambda s, z: [(1 + 0.5 * np.sin(0.2 * s)) * z[1], -z[0]], (0, 40),
                        [1.0, 0.0], t_eval=t, rtol=1e-10, atol=1e-10)
        x = sol.y.T + 0.01 * sol.y.T.std(axis=0) * rng.standard_normal((len(t), 2))
        theta = np.column_stack([np.ones(len(t)), x])
        scale = np.sqrt(np.mean(np.gradient(x, t, axis=0) ** 2, axis=0))
        vc = VaryingCoefficients([x], [t], [theta], scale, 0.01 * x.std(axis=0))
        model = vc.models[1]
        fit = model.fit((1,), ())
        assert fit.noise_variance / model.noise_variance < 1.3, random_times
        assert fit.constants[0] * scale[1] == pytest.approx(-1.0, abs=0.005)


def test_ar1_noise_is_whitened_in_the_integral_form():
    """xdot = y, ydot = -x under AR(1) noise of correlation 0.9 (1% of the std), 2000
    samples, 30 noise draws: with the noise's correlation the normal equations are
    whitened (generalised least squares), each window losing its first sample. The
    constant's estimate scatters about half as much as without (measured 0.53; bar
    0.7), its posterior standard deviation is 0.6-1.5 of that scatter (measured 0.75;
    white statistics: 0.61 of a scatter twice as wide), and its mean is unbiased."""
    t = np.linspace(0, 40, 2000)
    clean = np.column_stack([np.sin(t), np.cos(t)])
    sigma = 0.01 * clean.std(axis=0)
    theta_of = lambda x: np.column_stack([np.ones(len(t)), x])  # noqa: E731
    estimates, reported = {0.0: [], 0.9: []}, {0.0: [], 0.9: []}
    for seed in range(30):
        rng = np.random.default_rng(seed)
        e = np.zeros_like(clean)
        for k in range(1, len(t)):
            e[k] = 0.9 * e[k - 1] + np.sqrt(1 - 0.81) * rng.standard_normal(2)
        x = clean + sigma * e
        for phi in estimates:
            vc = VaryingCoefficients([x], [t], [theta_of(x)], np.ones(2), sigma,
                                     np.full(2, phi))
            fit = vc.models[1].fit((1,), ())
            estimates[phi].append(fit.constants[0])
            reported[phi].append(np.sqrt(fit.constant_cov[0, 0]))
    windows = len(vcm.window_starts(len(t), vc.window))
    white_n = LevelGram([x], [t], [theta_of(x)], vc.n_knots, vc.span, vc.window).n
    assert vc.models[1].g.n == white_n - windows
    scatter = {phi: np.std(v) for phi, v in estimates.items()}
    assert scatter[0.9] < 0.7 * scatter[0.0]
    assert 0.6 < np.median(reported[0.9]) / scatter[0.9] < 1.5
    assert abs(np.mean(estimates[0.9]) + 1.0) < 3 * scatter[0.9] / np.sqrt(30)
