"""Stage one: units, structure, repeatability and the generator's contract."""

import numpy as np
import pysindy as ps
import pytest
import torch

from latentsindy import CoefficientSeries, DynamicSINDy, systems
from latentsindy.generators import TimeVAE, TimeVAEOptions


def test_constant_system_gives_flat_true_coefficients():
    """Known constants come back flat, in physical units, within 2%."""
    data = systems.harmonic_oscillator(A=-2.0, B=1.5, t_end=20, n_times=1000, noise=0.01)
    # physical scaling far from 1 checks the exact un-normalisation
    x = data.x * np.array([300.0, 0.02])
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), verbose=False)
    coefs = model.fit(x, data.t, feature_names=["x", "y"]).coefficients(n_samples=8)
    a_true = -2.0 * 300.0 / 0.02
    b_true = 1.5 * 0.02 / 300.0
    assert coefs.active_terms() == [("x", "y"), ("y", "x")]
    a, b = coefs.term("x", "y"), coefs.term("y", "x")
    assert np.max(np.abs(a / a_true - 1)) < 0.02
    assert np.max(np.abs(b / b_true - 1)) < 0.02


def test_physical_units_exact_for_non_polynomial_library():
    """Pendulum with sin(theta): a Fourier + polynomial library, constants within 2%."""
    from scipy.integrate import solve_ivp

    t = np.linspace(0, 20, 1000)
    sol = solve_ivp(lambda _, s: [s[1], -3.0 * np.sin(s[0])], (0, 20), [2.0, 0.0],
                    t_eval=t, rtol=1e-10, atol=1e-10)
    x = sol.y.T
    lib = ps.PolynomialLibrary(degree=1, include_bias=False) + ps.FourierLibrary(n_frequencies=1)
    model = DynamicSINDy(lib, verbose=False)
    coefs = model.fit(x, t, feature_names=["q", "p"]).coefficients(n_samples=4)
    assert set(coefs.active_terms()) == {("q", "p"), ("p", "sin(1 q)")}
    assert np.max(np.abs(coefs.term("q", "p") - 1.0)) < 0.02
    assert np.max(np.abs(coefs.term("p", "sin(1 q)") + 3.0)) < 0.06


def test_encoder_conditions_on_data():
    """Different inputs give different latents, and the latent drives the coefficients.

    (The reference code's generator ignored its input.) Checked in two links so that
    the test does not rest on how strongly a randomly initialised decoder mixes z.
    """
    torch.manual_seed(0)
    gen = TimeVAE(4, 6, TimeVAEOptions())
    torch.nn.init.normal_(gen.to_coefficients.weight)  # the trained state: non-zero output
    t = torch.linspace(0, 20, 400)
    a = torch.stack([torch.sin(t), torch.cos(t), torch.cos(t), -torch.sin(t)])[None]
    b = torch.stack([torch.sin(2 * t), torch.cos(3 * t), t / 10, t**2 / 100])[None]
    with torch.no_grad():
        mu_a, _ = gen.encode(a)
        mu_b, _ = gen.encode(b)
        assert (mu_a - mu_b).norm() > 1e-2 * mu_a.norm()
        out_0 = gen.decode(torch.zeros(1, 4), 400)
        out_1 = gen.decode(torch.ones(1, 4), 400)
        assert (out_0 - out_1).abs().mean() > 0.05 * out_0.abs().mean()


def test_encoder_reads_long_series_at_the_decoders_resolution():
    """A series longer than ``n_knots`` is averaged down to ``n_knots`` points before the
    encoder: the latent is that of the average (so the encoder's cost stops growing
    with the length), and a short series is read as it is."""
    torch.manual_seed(0)
    options = TimeVAEOptions(n_knots=64)
    gen = TimeVAE(2, 3, options)
    long = torch.randn(1, 2, 1000)
    short = torch.randn(1, 2, 50)
    with torch.no_grad():
        pooled = torch.nn.functional.adaptive_avg_pool1d(long, 64)
        torch.testing.assert_close(gen.encode(long), gen.encode(pooled), rtol=0, atol=0)
        # the average is not a subsample: every sample counts
        changed = long.clone()
        changed[0, :, 3] += 5.0
        assert (gen.encode(changed)[0] - gen.encode(long)[0]).abs().max() > 1e-4
        short_latent = gen.encode(short)
        gen.encoder_points = None  # read every sample
        torch.testing.assert_close(gen.encode(short), short_latent, rtol=0, atol=0)


def test_knots_for_is_the_coarsest_grid_that_resolves_the_data():
    """The decoder's knots: a power of two between 32 and 256 with at least as many
    intervals as the data resolve, and no power of two below it would do."""
    from latentsindy.generators.timevae import MAX_KNOTS, knots_for

    for intervals in [0.5, 1, 30.9, 31, 31.01, 60.2, 63, 63.5, 100, 127, 128, 255, 256, 1e4]:
        knots = knots_for(intervals)
        assert 32 <= knots <= MAX_KNOTS and knots & (knots - 1) == 0
        assert knots - 1 >= intervals or knots == MAX_KNOTS
        assert knots == 32 or knots // 2 - 1 < intervals


def test_knots_follow_what_the_differentiator_resolves():
    """By default timeVAE's knots come from the data (one per half differentiator
    window, rounded up to a power of two): 2000 noise-free samples resolve more than
    256 (256 knots); 1% noise on prey-only Lotka-Volterra resolves about 60 intervals
    (64 knots, one upsampling convolution instead of three); a set ``n_knots`` is
    kept, and so are the options used, passed back in. The options used are on the
    fitted estimator and in the generator."""
    from latentsindy._stage_one.evidence import resolution
    from latentsindy.generators.timevae import knots_for

    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000, noise=0.01)
    x = data.x[:, :1]
    short = {"support_steps": 4, "refit_steps": 4}
    lib = ps.PolynomialLibrary(degree=2)
    noisy = DynamicSINDy(lib, verbose=False, training=short).fit(x, data.t)
    intervals = resolution(x, data.t)[0] - 3
    assert 40 < intervals < 90
    assert noisy.generator_options_.n_knots == knots_for(intervals) <= 128
    gen = noisy.model_.generator
    assert gen.options is noisy.generator_options_ and gen.encoder_points == knots_for(intervals)
    ups = [m for m in gen.upsample if isinstance(m, torch.nn.Conv1d)]
    assert 32 * 2 ** len(ups) == noisy.generator_options_.n_knots
    assert noisy.coefficients(n_samples=2).mean.shape == (2000, 1, 3)
    clean = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    fitted = DynamicSINDy(lib, verbose=False, training=short).fit(clean.x[:, :1], clean.t)
    assert fitted.generator_options_.n_knots == 256
    setting = {"n_knots": 256}
    kept = DynamicSINDy(lib, verbose=False, training=short,
                        generator_options=setting).fit(x, data.t)
    assert kept.generator_options_ == TimeVAEOptions(n_knots=256)
    assert kept.get_params()["generator_options"] is setting and setting == {"n_knots": 256}
    again = DynamicSINDy(lib, verbose=False, training=short,
                         generator_options=noisy.generator_options_).fit(x, data.t)
    assert again.generator_options_ == noisy.generator_options_
    np.testing.assert_array_equal(again.coefficients(n_samples=2).mean,
                                  noisy.coefficients(n_samples=2).mean)


@pytest.mark.parametrize("value", [0, -1, 16, 48, 100, 256.0, "64", True])
def test_knots_must_be_a_power_of_two_from_32_or_none(value):
    with pytest.raises(ValueError, match=r"n_knots must be a power of two >= 32, or None "
                                         r"\(chosen from the data\); got " + repr(value)):
        TimeVAEOptions(n_knots=value)


def test_options_of_another_generator_are_refused():
    from latentsindy.generators import HyperSINDyOptions

    data = systems.harmonic_oscillator(A=-1.0, n_times=300)
    with pytest.raises(TypeError, match=r"generator 'timevae' takes TimeVAEOptions or a dict "
                                        r"as options; got HyperSINDyOptions"):
        DynamicSINDy(verbose=False, generator_options=HyperSINDyOptions()).fit(data.x, data.t)


def test_parameter_count_bounded_whatever_the_length():
    """Noise-free series of 1000 and 8000 samples both get the most knots (256), so
    the same parameters; a noisy one gets fewer knots, so fewer parameters."""
    counts = []
    for n_times, noise in ((1000, 0.0), (8000, 0.0), (1000, 0.05)):
        data = systems.harmonic_oscillator(A=-1.0, n_times=n_times, noise=noise)
        model = DynamicSINDy(verbose=False, training={"support_steps": 2, "refit_steps": 2})
        counts.append(model.fit(data.x, data.t).n_parameters_)
        assert model.coefficients(n_samples=2).mean.shape[0] == n_times
        assert (model.generator_options_.n_knots == 256) == (noise == 0)
    assert counts[0] == counts[1] < 50_000
    assert counts[2] < counts[1]


def test_seed_makes_runs_repeatable(fast):
    data = systems.harmonic_oscillator(A=-1.0, n_times=300)
    runs = [DynamicSINDy(verbose=False, training=fast, seed=3).fit(data.x, data.t)
            .coefficients(n_samples=4) for _ in range(2)]
    np.testing.assert_array_equal(runs[0].mean, runs[1].mean)
    np.testing.assert_array_equal(runs[0].samples, runs[1].samples)


def test_coefficients_asked_twice_are_the_same(fast):
    """The posterior samples are scaled in place and given to the result: nothing the
    model keeps is touched, so a second call gives the first's arrays again."""
    data = systems.harmonic_oscillator(A=-1.0, n_times=300)
    model = DynamicSINDy(verbose=False, training=fast, seed=2).fit(data.x, data.t)
    first, second = model.coefficients(n_samples=4), model.coefficients(n_samples=4)
    for name in ("mean", "std", "samples", "lower", "upper"):
        assert np.array_equal(getattr(first, name), getattr(second, name)), name
    assert not first.samples.flags.writeable and first.samples is not second.samples


def test_result_object(fast):
    data = systems.harmonic_oscillator(A=-1.0, n_times=300)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), verbose=False, training=fast)
    assert model.fit(data.x, data.t, feature_names=["x", "y"]) is model
    c = model.coefficients(n_samples=5)
    assert isinstance(c, CoefficientSeries)
    assert c.mean.shape == c.std.shape == (300, 2, 6)
    assert c.samples.shape == (5, 300, 2, 6)
    assert c.feature_names == ("1", "x", "y", "x^2", "x y", "y^2")
    assert c.state_names == ("x", "y")
    assert c.noise_across_samples.shape == c.noise_around_smooth_mean.shape == (2, 6)
    np.testing.assert_allclose(c.times, data.t)
    with pytest.raises(ValueError, match="read-only"):
        c.mean[0, 0, 0] = 1.0
    assert "dx/dt" in c.summary()


def test_fixed_support_and_constant_terms(fast):
    data = systems.harmonic_oscillator(A=-1.0, B=systems.Sigmoid(1.0, 2.0, at=5.0), n_times=400)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=1, include_bias=False), verbose=False,
                         training=fast, support={"x": ["y"]}, time_varying={"y": ["x"]})
    c = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(n_samples=4)
    assert c.support[0].tolist() == [False, True]
    assert c.time_varying.tolist() == [[False, False], [bool(c.support[1, 0]), False]]
    assert np.ptp(c.term("x", "y")) == 0.0  # constant terms are exactly flat


def test_several_trajectories_share_dynamics(fast):
    a = systems.harmonic_oscillator(A=-1.0, n_times=300, x0=(1.0, 0.0))
    b = systems.harmonic_oscillator(A=-1.0, n_times=300, x0=(0.0, 2.0))
    model = DynamicSINDy(verbose=False, training=fast).fit([a.x, b.x], [a.t, b.t])
    assert model.coefficients(n_samples=2).mean.shape == (300, 2, 6)
    assert len(model.predict()) == 2


def test_given_derivatives_are_used(fast):
    data = systems.harmonic_oscillator(A=-1.0, n_times=300)
    given = DynamicSINDy(verbose=False, training=fast).fit(data.x, data.t, x_dot=data.x_dot)
    estimated = DynamicSINDy(verbose=False, training=fast).fit(data.x, data.t)
    np.testing.assert_array_equal(given.x_dot_[0], data.x_dot)
    assert not np.array_equal(given.coefficients(2).mean, estimated.coefficients(2).mean)


def test_user_arrays_stay_writable_and_unchanged(fast):
    data = systems.harmonic_oscillator(A=-1.0, n_times=300)
    t = data.t.copy()
    DynamicSINDy(verbose=False, training=fast).fit(data.x, t).coefficients(n_samples=2)
    t[0] = 0.0  # would raise if the result had frozen the caller's array
    np.testing.assert_array_equal(t, data.t)


def test_list_of_rows_is_one_trajectory(fast):
    data = systems.harmonic_oscillator(A=-1.0, n_times=200)
    model = DynamicSINDy(verbose=False, training=fast).fit(data.x.tolist(), data.dt)
    assert len(model.x_) == 1 and model.x_[0].shape == (200, 2)


def test_get_and_set_params():
    model = DynamicSINDy(seed=4)
    assert model.get_params()["seed"] == 4
    assert model.set_params(seed=5).seed == 5
    with pytest.raises(ValueError, match=r"Unknown parameter\(s\) \['sed'\]"):
        model.set_params(sed=1)


def test_predict_before_fit():
    with pytest.raises(RuntimeError, match="not fitted yet"):
        DynamicSINDy().predict()


def _series(values, t):
    from latentsindy import CoefficientSeries

    mean = np.asarray(values, dtype=float)[:, None, None]
    return CoefficientSeries.from_samples(t, mean, mean[None], ["x"], ["y"],
                                          np.ones((1, 1), bool), np.ones((1, 1), bool))


def test_switch_times_against_known_switches():
    t = np.linspace(0.0, 20.0, 2000)
    two = _series(systems.Switches((-1.0, -3.0, -1.5), (7.0, 14.0))(t), t)
    assert np.allclose(two.switch_times(), [7.0, 14.0], atol=0.05)
    sigmoid = _series(systems.Sigmoid(-1.0, -4.0, at=12.0, sharpness=1.0)(t), t)
    assert np.allclose(sigmoid.switch_times(), [12.0], atol=0.2)  # one, at the middle
    flat = _series(-2.0 + 0.01 * np.sin(t), t)
    assert flat.switch_times().size == 0
    with pytest.raises(ValueError, match="window must be between 1 and half the series"):
        flat.switch_times(window=1500)
    assert np.allclose(two.switch_times(terms=[("x", "y")]), [7.0, 14.0], atol=0.05)
    with pytest.raises(KeyError, match="Unknown feature 'z'"):
        two.switch_times(terms=[("x", "z")])


def test_coefficient_noise_from_residuals_matches_the_truth():
    """A and B carry white noise of std 0.2 (the paper's uncertainty experiment, exact
    derivatives): the method-of-moments estimate recovers it within 15%; the posterior
    spread does not (it is the uncertainty of the smooth mean)."""
    data = systems.harmonic_oscillator(A=-2.0, B=1.0, t_end=25.0, n_times=1000,
                                       coefficient_noise=0.2, seed=3)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=1, include_bias=False), verbose=False,
                         training={"support_steps": 200, "refit_steps": 200})
    model.fit(data.x, data.t, x_dot=data.x_dot, feature_names=["x", "y"])
    noise = model.coefficient_noise()
    np.testing.assert_allclose([noise[0, 1], noise[1, 0]], 0.2, rtol=0.15)
    assert noise[0, 0] == 0 and noise[1, 1] == 0  # outside the support
    quiet = systems.harmonic_oscillator(A=-2.0, B=1.0, t_end=25.0, n_times=1000)
    clean = DynamicSINDy(ps.PolynomialLibrary(degree=1, include_bias=False), verbose=False,
                         training={"support_steps": 200, "refit_steps": 200})
    clean.fit(quiet.x, quiet.t, x_dot=quiet.x_dot, feature_names=["x", "y"])
    assert clean.coefficient_noise().max() < 0.02  # no noise: (almost) none found
    with pytest.raises(RuntimeError, match="not fitted"):
        DynamicSINDy().coefficient_noise()
