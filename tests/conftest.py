import numpy as np
import pytest
import torch

torch.set_num_threads(2)


def pytest_addoption(parser):
    parser.addoption("--runslow", action="store_true", default=False,
                     help="also run the tests marked slow (accuracy at default settings "
                          "that trains for minutes: dynamic HyperSINDy's)")


def pytest_collection_modifyitems(config, items):
    """Tests marked slow are skipped, with the reason, unless ``--runslow`` is given:
    CI runs the suite without them (they take minutes each)."""
    if config.getoption("--runslow"):
        return
    skip = pytest.mark.skip(reason="slow (minutes): run with --runslow")
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(skip)


@pytest.fixture(autouse=True)
def fresh_map_pace():
    """The second process's size rule (:data:`latentsindy._core.parallel.FORK_WORTH`)
    remembers each map's pace in the process, and the AR(1) noise reading its last
    readings, and the smoother its last weighted integrals: every test begins without
    these memories, as a fresh process would, so that which maps fork, and what is
    computed afresh, do not depend on the tests before it."""
    from latentsindy._core import coloured, parallel
    from latentsindy._stage_two.propose import smoother

    parallel._SECONDS_PER_ITEM.clear()
    coloured._READ.clear()  # and without the noise readings kept by content
    smoother._PRODUCTS.clear()  # nor the smoother's weighted integrals
    yield
    parallel.reap_helpers()


def r2(estimate, truth):
    """Coefficient of determination of ``estimate`` against ``truth``."""
    estimate, truth = np.asarray(estimate), np.asarray(truth)
    return 1.0 - np.sum((estimate - truth) ** 2) / np.sum((truth - truth.mean()) ** 2)


def transition_time(t, series, low, high):
    """First time the series crosses the midpoint between ``low`` and ``high``."""
    mid = 0.5 * (low + high)
    above = (series - mid) * np.sign(high - low) > 0
    return float(t[np.argmax(above)])


LORENZ_TERMS = [("x", "x"), ("x", "y"), ("y", "x"), ("y", "y"), ("y", "x z"), ("z", "z"),
                ("z", "x y")]
LORENZ_CONSTANTS = {("y", "x"): 28.0, ("y", "y"): -1.0, ("y", "x z"): -1.0, ("z", "x y"): 1.0,
                    ("z", "z"): -8.0 / 3.0}


def check_lorenz(coefs, data):
    """Lorenz with a time-varying sigma: exact support, R^2 of sigma(t) >= 0.9 in both
    terms where it appears, the other coefficients within 5%."""
    assert coefs.active_terms() == LORENZ_TERMS
    assert r2(coefs.term("x", "y"), data.parameters["sigma"]) >= 0.9
    assert r2(-coefs.term("x", "x"), data.parameters["sigma"]) >= 0.9
    for (state, feature), value in LORENZ_CONSTANTS.items():
        assert abs(coefs.term(state, feature).mean() / value - 1) < 0.05, (state, feature)


@pytest.fixture(scope="session")
def lv():
    """Noise-free prey-only Lotka-Volterra at T=2000 (the tutorial), default settings."""
    import pysindy as ps

    from latentsindy import discover_hidden, systems

    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=2000)
    result = discover_hidden(data.x[:, :1], ps.PolynomialLibrary(degree=3, include_bias=False),
                             t=data.t, feature_names=["x"], hidden_names=["h"], verbose=False)
    return data, result


@pytest.fixture
def fast():
    """Training options for tests that check plumbing rather than accuracy."""
    return {"support_steps": 40, "refit_steps": 40}
