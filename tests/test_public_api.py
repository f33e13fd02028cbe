"""The public surface: namespaces, moved names, typed doubts, one-line reprs and a
configured stage one passed to discover_hidden."""

import dataclasses
import pickle

import pysindy as ps
import pytest

import latentsindy
from latentsindy import DynamicSINDy, discover_hidden, load, options, results, systems
from latentsindy.results import Doubt

MOVED = {"HiddenComparison": results, "HiddenState": results, "Term": results,
         "Alternative": results, "Refinement": results, "DataUse": results,
         "Simulation": results, "TrainingOptions": options,
         "SequentialTrainingOptions": options}


def test_top_level_keeps_the_verbs_and_main_classes():
    assert set(latentsindy.__all__) == {
        "discover_hidden", "discover_many", "DynamicSINDy", "load", "HiddenDiscovery",
        "CoefficientSeries", "Run", "results", "options", "systems", "generators",
        "celegans", "baselines", "__version__"}
    for name in latentsindy.__all__:
        assert hasattr(latentsindy, name), name
    for module in (results, options):
        for name in module.__all__:
            assert hasattr(module, name), (module.__name__, name)
    assert latentsindy.__version__ == "0.2.0"
    # what a user sees with dir() or tab completion is the public surface alone
    public = {n for n in dir(latentsindy) if not n.startswith("_")}
    assert public == set(latentsindy.__all__) - {"__version__"}


@pytest.mark.parametrize("name", sorted(MOVED))
def test_moved_names_still_import_with_a_warning_naming_the_new_place(name):
    where = MOVED[name].__name__
    with pytest.warns(DeprecationWarning, match=rf"moved to {where}\.{name}"):
        obj = getattr(latentsindy, name)
    assert obj is getattr(MOVED[name], name)


def test_unknown_top_level_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no attribute 'discover'"):
        latentsindy.discover  # noqa: B018


def test_doubt_is_its_message_with_a_kind():
    d = Doubt("weak term", "the data support x only weakly")
    assert d == "the data support x only weakly" and "weakly" in d
    assert d.kind == "weak term" and d.message == str(d) and type(d.message) is str
    assert repr(d) == "Doubt('weak term', 'the data support x only weakly')"
    back = pickle.loads(pickle.dumps(d))
    assert type(back) is Doubt and back.kind == "weak term" and back == d
    assert "weak term" in Doubt.kinds()


def test_doubt_errors_say_what_is_valid():
    with pytest.raises(ValueError, match=r"kind must be one of .*'weak term'.*got 'weak'"):
        Doubt("weak", "text")
    with pytest.raises(TypeError, match="message must be a str; got int"):
        Doubt("weak term", 3)


def test_result_repr_is_one_line_and_str_is_the_summary(lv):
    _, result = lv
    text = repr(result)
    assert "\n" not in text and len(text) < 200
    assert text.startswith("HiddenDiscovery(1 observed + 1 hidden: x, h; confident")
    assert str(result) == result.summary()
    doubted = dataclasses.replace(result, doubts=("a plain sentence",))
    assert "not confident" in repr(doubted) and "1 doubt" in repr(doubted)
    assert doubted.doubts[0].kind == "unspecified"  # plain text becomes a Doubt


def test_every_doubt_of_a_discovery_is_typed_and_kinds_survive_a_file(lv, tmp_path):
    _, result = lv
    doubted = dataclasses.replace(result, doubts=(Doubt("missing term", "m"),
                                                  Doubt("free run", "f")))
    path = tmp_path / "r.npz"
    doubted.save(path)
    back = load(path)
    assert [(d.kind, str(d)) for d in back.doubts] == [("missing term", "m"), ("free run", "f")]
    assert all(isinstance(d, Doubt) for d in back.coefficients.doubts)


@pytest.fixture(scope="module")
def small_lv():
    data = systems.lotka_volterra(1.0, 0.1, 1.5, 0.075, n_times=600)
    return data.x[:, :1], data.t


def test_discover_hidden_takes_a_configured_stage_one(small_lv, monkeypatch):
    """Every parameter of the model reaches stage one; device, seed and verbose are the
    call's; the model passed in is not changed."""
    made = []

    def recording_fit(self, *args, **kwargs):
        made.append(self.get_params())
        raise RuntimeError("stop after stage one's parameters")

    monkeypatch.setattr(DynamicSINDy, "fit", recording_fit)
    library = ps.PolynomialLibrary(degree=2)
    model = DynamicSINDy(library, structure="all", time_varying=[("x", "x")],
                         training={"support_steps": 5}, seed=7, verbose=True)
    before = model.get_params()
    x, t = small_lv
    with pytest.raises(RuntimeError, match="stop after"):
        discover_hidden(x, t=t, model=model, feature_names=["x"], seed=3, verbose=False)
    assert made[0]["library"] is library and made[0]["structure"] == "all"
    assert made[0]["time_varying"] == [("x", "x")]
    assert made[0]["training"] == {"support_steps": 5}
    assert (made[0]["seed"], made[0]["verbose"]) == (3, False)
    assert model.get_params() == before


def test_discover_hidden_refuses_a_model_and_its_options_at_once(small_lv):
    x, t = small_lv
    model = DynamicSINDy(ps.PolynomialLibrary(degree=2))
    with pytest.raises(ValueError, match=r"\['generator', 'training'\] set both here and by "
                                         r"model="):
        discover_hidden(x, t=t, model=model, generator="hypersindy", training={})
    with pytest.raises(ValueError, match=r"\['library'\] set both"):
        discover_hidden(x, ps.PolynomialLibrary(degree=3), t=t, model=model)
    with pytest.raises(TypeError, match="model must be a DynamicSINDy .* got dict"):
        discover_hidden(x, t=t, model={"library": None})



def test_dynamic_sindy_repr_shows_what_differs_from_the_defaults():
    assert repr(DynamicSINDy()) == "DynamicSINDy()"
    model = DynamicSINDy(ps.PolynomialLibrary(degree=3), seed=3, verbose=False)
    assert repr(model) == "DynamicSINDy(library=PolynomialLibrary(degree=3), verbose=False, seed=3)"


def test_coefficient_series_repr_is_one_line_with_typed_doubts(lv):
    _, result = lv
    coefs = result.coefficients
    text = repr(coefs)
    assert "\n" not in text
    assert text.startswith("CoefficientSeries(2000 times, 1 term, varying: x in dx/dt")
    assert str(coefs) == coefs.summary()
    assert all(isinstance(d, Doubt) and d.kind in Doubt.kinds() for d in coefs.doubts)
