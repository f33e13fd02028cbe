"""Every bad input raises at the boundary with a message that says the fix."""

import numpy as np
import pysindy as ps
import pytest
import torch

from latentsindy import DynamicSINDy, discover_hidden, systems


@pytest.fixture(scope="module")
def data():
    return systems.harmonic_oscillator(A=-1.0, B=1.0, n_times=200)


def fit(x, t, **kw):
    lib = kw.pop("library", ps.PolynomialLibrary(degree=1))
    init = {"training": {"support_steps": 2, "refit_steps": 2}} | kw.pop("init", {})
    model = DynamicSINDy(lib, verbose=False, **init)
    return model.fit(x, t, **kw)


def test_nan_in_x(data):
    x = data.x.copy()
    x[17, 1] = np.nan
    with pytest.raises(ValueError, match=r"NaN or infinite.*row 17"):
        fit(x, data.t)


def test_inf_in_x(data):
    x = data.x.copy()
    x[3, 0] = np.inf
    with pytest.raises(ValueError, match="NaN or infinite"):
        fit(x, data.t)


def test_wrong_shape(data):
    with pytest.raises(ValueError, match=r"shape \(n_times, n_states\); got shape \(2, 200, 2\)"):
        fit(np.stack([data.x, data.x]), data.t)


def test_not_numeric():
    with pytest.raises(TypeError, match=r"real numbers.*got a string array \(dtype <U1\)"):
        fit(np.array([["a", "b"]] * 20), 0.1)


def test_t_not_increasing(data):
    t = data.t.copy()
    t[50] = t[49]
    with pytest.raises(ValueError, match=r"strictly increasing; t\[49\]=[0-9.]+ is followed by "
                                         r"t\[50\]=[0-9.]+\. Sort the samples"):
        fit(data.x, t)


def test_length_mismatch(data):
    with pytest.raises(ValueError, match="Length mismatch: t has 199 times but x has 200 rows"):
        fit(data.x, data.t[:-1])


def test_transposed_x_is_named(data):
    """States in rows and samples in columns: the message says to pass x.T."""
    with pytest.raises(ValueError, match=r"Length mismatch: t has 200 times but x has 2 rows; "
                                         r"they must match\. x is read with one row per "
                                         r"sample.*pass x\.T\."):
        discover_hidden(data.x.T, t=data.t, verbose=False)
    with pytest.raises(ValueError, match=r"got shape \(1, 200\): at least 16 samples.*It looks "
                                         r"transposed.*pass x\.T\."):
        fit(data.x[:, :1].T, 0.1)
    with pytest.raises(ValueError, match=r"Series too short.*2 time points.*It looks "
                                         r"transposed.*pass x\.T\."):
        fit(data.x.T, 0.1)


def test_a_transposed_recording_in_a_list_is_named(data):
    with pytest.raises(ValueError, match=r"trajectory 0 of x has 2 time points.*pass x\[0\]\.T\."):
        fit([data.x.T, data.x.T], 0.1)


def test_too_few_rows_are_not_called_transposed(data):
    with pytest.raises(ValueError, match="Series too short.*10 time points") as info:
        fit(data.x[:10], 0.1)
    assert "transposed" not in str(info.value)
    with pytest.raises(ValueError, match="t has 199 times but x has 200 rows") as info:
        fit(data.x, data.t[:-1])
    assert "x.T" not in str(info.value)


def test_bad_spacing(data):
    with pytest.raises(ValueError, match="sample spacing t must be a positive number; "
                                         r"got -0\.1\."):
        fit(data.x, -0.1)
    with pytest.raises(ValueError, match=r"positive number; got -0\.5\.$"):
        fit(data.x, np.float64(-0.5))


def test_series_too_short(data):
    with pytest.raises(ValueError, match="Series too short.*10 time points"):
        fit(data.x[:10], data.t[:10])


def test_empty_library(data):
    lib = ps.CustomLibrary(library_functions=[], function_names=[])
    with pytest.raises(ValueError, match="library is empty"):
        fit(data.x, data.t, library=lib)


def test_library_wrong_type(data):
    with pytest.raises(TypeError, match="pysindy feature library.*; got str"):
        fit(data.x, data.t, library="poly")
    with pytest.raises(TypeError, match=r"library must be a pysindy feature library object; "
                                        r"got the class PolynomialLibrary itself: call it, e\.g\. "
                                        r"PolynomialLibrary\(\) with its settings\."):
        fit(data.x, data.t, library=ps.PolynomialLibrary)


def test_x_dot_shape(data):
    with pytest.raises(ValueError, match="x_dot shapes"):
        fit(data.x, data.t, x_dot=data.x_dot[:, :1])


def test_feature_names_count(data):
    with pytest.raises(ValueError, match="has 3 names but the data have 2 states"):
        fit(data.x, data.t, feature_names=["x", "y", "z"])


def test_trajectories_differ_in_states(data):
    with pytest.raises(ValueError, match="same number of states"):
        fit([data.x, data.x[:, :1]], data.t)


def test_trajectories_on_different_grids(data):
    with pytest.raises(ValueError, match="same time grid"):
        fit([data.x, data.x[:150]], [data.t, data.t[:150]])


def test_misspelt_training_option(data):
    with pytest.raises(TypeError, match=r"Unknown training option\(s\) \['treshold'\]"):
        fit(data.x, data.t, init={"training": {"treshold": 0.1}})


def test_bad_training_value(data):
    with pytest.raises(ValueError, match="learning_rate must be > 0"):
        fit(data.x, data.t, init={"training": {"learning_rate": 0.0}})


def test_misspelt_generator_option(data):
    with pytest.raises(TypeError, match=r"Unknown option\(s\) \['latent'\] for generator"):
        fit(data.x, data.t, init={"generator_options": {"latent": 3}})


def test_unknown_generator(data):
    with pytest.raises(ValueError, match="generator must be one of"):
        fit(data.x, data.t, init={"generator": "gan"})


def test_support_unknown_feature(data):
    with pytest.raises(ValueError, match=r"support\['x'\] names feature 'q'"):
        fit(data.x, data.t, feature_names=["x", "y"], init={"support": {"x": ["q"]}})


def test_support_unknown_state(data):
    with pytest.raises(ValueError, match="support names state 'w'"):
        fit(data.x, data.t, feature_names=["x", "y"], init={"support": {"w": ["x"]}})


def test_coefficients_before_fit():
    with pytest.raises(RuntimeError, match="not fitted yet"):
        DynamicSINDy().coefficients()


def test_bad_seed(data):
    with pytest.raises(ValueError, match="seed must be a non-negative int; got -1"):
        fit(data.x, data.t, init={"seed": -1})
    with pytest.raises(TypeError, match="seed must be a non-negative int; got True"):
        fit(data.x, data.t, init={"seed": True})


def test_device_must_exist(data):
    with pytest.raises(ValueError, match=r"device must be 'cpu' or a CUDA device .*got 'tpu'"):
        DynamicSINDy(ps.PolynomialLibrary(degree=2), device="tpu").fit(data.x, data.t)
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    with pytest.raises(ValueError, match=rf"device 'cuda:{count}' is not available: this "
                                         rf"machine has {count} CUDA device\(s\)"):
        DynamicSINDy(ps.PolynomialLibrary(degree=2), device=f"cuda:{count}").fit(data.x, data.t)
    with pytest.raises(ValueError, match="got 'gpu'"):
        discover_hidden(data.x[:, :1], t=data.t, device="gpu", verbose=False)
