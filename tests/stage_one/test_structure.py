"""Stage one's structure chosen by evidence, its band and its doubts (issue 19).

The paper's Lorenz case that stage one used to lose: rho varies, and a generator drops
the small constant -y of ydot, letting rho(t) x absorb it. The exact
varying-coefficient model decides support and variation together.
"""

import numpy as np
import pysindy as ps
import pytest
from conftest import r2

import latentsindy
from latentsindy import DynamicSINDy, systems

QUICK = {"support_steps": 300, "refit_steps": 300}


@pytest.fixture(scope="module")
def rho_sigmoid():
    rho = systems.Sigmoid(24.0, 34.0, at=10.0, sharpness=0.5)
    data = systems.lorenz(rho=rho, n_times=2000, t_end=20.0, noise=0.01, seed=0)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), training=QUICK, verbose=False)
    model.fit(data.x, data.t, feature_names=["x", "y", "z"])
    return data, model, model.coefficients(n_samples=8)


def test_a_varying_rho_keeps_every_constant_term(rho_sigmoid):
    """Exact support (with -y), only rho varies, rho's R^2 >= 0.99, constants within 2%
    (measured: R^2 0.9996, constants within 0.8%)."""
    data, model, coefs = rho_sigmoid
    truth = sorted(k for k, v in data.terms.items() if np.any(v != 0))
    assert sorted(coefs.active_terms()) == truth
    rows, cols = np.nonzero(coefs.time_varying)
    assert [(coefs.state_names[i], coefs.feature_names[j]) for i, j in zip(rows, cols,
                                                                            strict=True)] == [
        ("y", "x")]
    assert r2(coefs.term("y", "x"), data.terms[("y", "x")]) >= 0.99
    for (s, f), v in data.terms.items():
        if np.ptp(v) == 0 and v[0] != 0:
            assert np.mean(coefs.term(s, f)) == pytest.approx(v[0], rel=0.02)
    assert model.doubts_ == ()


def test_the_band_holds_the_truth(rho_sigmoid):
    """The band holds the true rho(t) at >= 85% of the samples and is no wider than 3x
    the actual RMS error (measured: 100%, 1.6x)."""
    data, _, coefs = rho_sigmoid
    lo, hi = coefs.term_band("y", "x")
    truth = data.terms[("y", "x")]
    assert np.mean((lo <= truth) & (truth <= hi)) >= 0.85
    error = np.sqrt(np.mean((coefs.term("y", "x") - truth) ** 2))
    assert np.mean(coefs.half_width[:, 1, 1]) <= 3 * error + 0.05
    np.testing.assert_array_equal(coefs.lower[:, 0, 0], 0.0)  # off support: nothing


def test_band_and_doubts_survive_the_model_file(rho_sigmoid, tmp_path):
    _, model, coefs = rho_sigmoid
    model.save(tmp_path / "m.npz")
    back = latentsindy.load(tmp_path / "m.npz").coefficients(n_samples=8)
    np.testing.assert_allclose(back.lower, coefs.lower)
    np.testing.assert_allclose(back.upper, coefs.upper)
    assert back.doubts == coefs.doubts


def test_the_generator_can_decide_and_is_checked_anyway():
    """structure="generator" is the paper's method: the exact model does not change the
    fit, but says when it prefers another structure. Lorenz with a linear library:
    timeVAE lets every term vary (x's equation too, whose coefficients are constant)."""
    data = systems.lorenz(n_times=1000, t_end=10.0, noise=0.01, seed=0)
    lib = ps.PolynomialLibrary(degree=1)
    model = DynamicSINDy(lib, structure="generator", training=QUICK, verbose=False)
    model.fit(data.x, data.t, feature_names=["x", "y", "z"])
    assert "dx/dt: the exact model prefers a structure x constant, y constant" in " ".join(
        model.doubts_)
    assert model.coefficients(2).doubts == model.doubts_
    assert "DOUBTS" in model.coefficients(2).summary()


def test_a_misspelt_structure_option_is_refused():
    data = systems.harmonic_oscillator(A=-2.0, B=1.0, n_times=200)
    with pytest.raises(ValueError, match=r"structure must be one of \('evidence', "
                                         r"'generator'\); got 'evidense'"):
        DynamicSINDy(structure="evidense", verbose=False).fit(data.x, data.t)


def test_slowly_varying_stiffness_band():
    """The issue's oscillator: a slowly varying stiffness at 2% noise. The old band
    (posterior spread) was 0.0016 wide against an error of about 0.02 and held the
    truth at 13% of the samples; the band must hold it at >= 85%, no wider than 3x the
    RMS error."""
    t_end = 30.0
    stiffness = systems.Sinusoid(-1.5, 0.5, 1.0 / 40.0)  # less than a cycle over the series
    data = systems.harmonic_oscillator(A=stiffness, B=1.0, t_end=t_end, n_times=1500,
                                       noise=0.02, seed=3)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=1, include_bias=False), training=QUICK,
                         verbose=False)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(n_samples=8)
    truth = data.terms[("x", "y")]
    lo, hi = coefs.term_band("x", "y")
    assert np.mean((lo <= truth) & (truth <= hi)) >= 0.85
    error = np.sqrt(np.mean((coefs.term("x", "y") - truth) ** 2))
    assert np.mean(0.5 * (hi - lo)) <= 3 * error


def test_an_equation_the_library_cannot_express_is_a_doubt():
    """Lorenz with a linear library and no variation allowed in ydot and zdot: their
    x z and x y terms are missing, and the exact model's misfit says so."""
    data = systems.lorenz(n_times=1000, t_end=10.0, noise=0.01, seed=0)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=1), time_varying={"x": ["x"]},
                         training=QUICK, verbose=False)
    model.fit(data.x, data.t, feature_names=["x", "y", "z"])
    misfit = [d for d in model.doubts_ if "misfit of" in d]
    assert [d.split(":")[0] for d in misfit] == ["dy/dt", "dz/dt"]


def test_the_adaptive_evidence_chooses_between_the_searches_optima():
    """Rucklidge's system seen through x and y at 1% noise (a fresh system, draw 1):
    dx/dt = -k x + (l - z) y. The search from the generator's proposal ends at a varying
    constant and a varying y^2 (which absorb anything), the one from the thresholded
    constant fit at x and a varying y; the Gaussian slope priors prefer the first by 80
    nats, the adaptive ones, the search's criterion, the second by 143. Judged by the
    adaptive evidence, the true structure is chosen (before, the first was)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from _families import ALL_FAMILIES, draw

    d = draw("rucklidge", 1, 0.01)
    model = DynamicSINDy(ALL_FAMILIES["rucklidge"].library(), verbose=False, seed=0)
    model.fit(d.observed, d.t, feature_names=list(d.observed_names))
    coefs = model.coefficients(n_samples=8)
    assert sorted(f for s, f in coefs.active_terms() if s == "x") == ["x", "y"]
    assert model.time_varying_[0].tolist() == [f == "y" for f in model.feature_names_]
    assert coefs.term("x", "x").mean() == pytest.approx(-d.params["k"], rel=0.02)


def test_the_papers_switching_cases_at_seed_1(monkeypatch):
    """Two of the seed paper's cases at its seed 1 (1% noise).

    Lorenz with a switching sigma: with line searches of 20 trials on noisy
    forward-difference gradients, the Gaussian search's best was x, y and z^2 varying,
    and the adaptive climb from another start ended at a wrong local optimum 130 nats
    below the truth: a doubt on a right answer. With 8 trials (as with the exact
    gradient, tried and not adopted for its cost) the Gaussian best is the truth,
    dx/dt = sigma(t) (y - x), and no doubt is left.

    The oscillator with a switching A (dx/dt = A(t) y): the Gaussian best (a varying
    constant and a varying y) climbs to a varying constant beside a constant y, 4.4
    nats above the truth, where the other start ends. The evidence cannot tell these
    apart by much: the doubt is said, and the band holds both ends."""
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from _paper_cases import lorenz_cases, make_data, oscillator_cases

    case = next(c for c in lorenz_cases() if c.name == "lorenz sigma switch")
    data, _ = make_data(case, seed=1)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), verbose=False, seed=1)
    model.fit(data.x, data.t, feature_names=["x", "y", "z"])
    names = model.feature_names_
    assert [names[j] for j in np.flatnonzero(model.support_[0])] == ["x", "y"]
    assert [names[j] for j in np.flatnonzero(model.time_varying_[0])] == ["x", "y"]
    assert not [d for d in model.doubts_ if d.startswith("dx/dt")]

    apart = "the structure search from another start ended at"
    case = next(c for c in oscillator_cases() if c.name == "oscillator A switch")
    data, _ = make_data(case, seed=1)
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2), verbose=False, seed=1)
    coefs = model.fit(data.x, data.t, feature_names=["x", "y"]).coefficients(n_samples=4)
    doubt = [d for d in model.doubts_ if apart in d]
    assert len(doubt) == 1 and doubt[0].startswith("dx/dt") and "y varying" in doubt[0]
    truth = data.terms[("x", "y")]
    lower, upper = coefs.term_band("x", "y")
    assert np.mean((lower <= truth) & (truth <= upper)) > 0.9
    # the exact model's band holds the truth through the other end: the chosen
    # structure's own interval (a constant y) does not
    a, j = model.assessment_, model.feature_names_.index("y")
    inside = (a.lower[:, 0, j] <= truth) & (truth <= a.upper[:, 0, j])
    own = np.abs(a.mean[:, 0, j] - truth) <= 2 * a.sd[:, 0, j]
    assert np.mean(inside) > 0.9 and np.mean(own) < 0.5
