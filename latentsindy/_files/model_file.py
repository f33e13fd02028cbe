"""The model file: a fitted :class:`DynamicSINDy`.

One ``.npz`` file: the network's weights as plain arrays (its ``state_dict``), the
fitted arrays, and one JSON document with the settings. Nothing is unpickled and no
text is evaluated: the network is rebuilt from its settings and the weights are loaded
into it with ``strict=True``, so a file that does not match is refused. The feature
library is stored for pysindy's polynomial and Fourier libraries; a model with another
library loads without it (``coefficients()`` works, ``predict()`` says what is missing).
"""

from __future__ import annotations

import dataclasses
import json

import pysindy as ps
import torch

from .._core import saving
from .._core.doubt import as_doubts, read_doubts
from .._core.library import fit_library
from .._stage_one.assessment import Assessment
from .._stage_one.coefficient_model import CoefficientModel
from .._stage_one.estimator import DynamicSINDy, sample_positions
from .._stage_one.sequential_model import SequentialCoefficientModel
from ..generators import build_generator, generator_class
from .container import write

FORMAT = "latentsindy.DynamicSINDy"
# 2: pinned constants, the structure setting, the exact model's band; 3: timeVAE's
# encoder reads a long series averaged down to its knots (older files: every sample);
# 4: the generator's options as built (timeVAE's knots chosen from the data; older
# files were built from their settings, timeVAE with 256 knots unless set)
VERSION = 4
READABLE = (1, 2, 3, 4)
_SETTINGS = ("generator", "generator_options", "training", "structure", "support",
             "time_varying", "seed")


def _library_spec(library):
    if type(library) is ps.PolynomialLibrary:
        return {"kind": "polynomial", "degree": int(library.degree),
                "include_bias": bool(library.include_bias),
                "include_interaction": bool(library.include_interaction),
                "interaction_only": bool(library.interaction_only)}
    if type(library) is ps.FourierLibrary:
        return {"kind": "fourier", "n_frequencies": int(library.n_frequencies),
                "include_sin": bool(library.include_sin), "include_cos": bool(library.include_cos)}
    return None


def _library(spec, trajectories, names):
    if spec is None:
        return None
    kind = spec.pop("kind")
    lib = (ps.PolynomialLibrary if kind == "polynomial" else ps.FourierLibrary)(**spec)
    fit_library(lib, trajectories, list(names))
    return lib


def _jsonable(value):
    if dataclasses.is_dataclass(value):
        return dataclasses.asdict(value)
    return value


@saving.save.register
def save_model(model: DynamicSINDy, path) -> None:
    """Write a fitted DynamicSINDy to ``path`` (``.npz``)."""
    model._check_fitted()
    settings = {k: _jsonable(getattr(model, k)) for k in _SETTINGS}
    try:
        json.dumps(settings)
    except TypeError as err:
        raise ValueError(f"DynamicSINDy settings cannot be stored ({err}); pass options as "
                         "dicts or the package's options classes.") from None
    m = model.model_
    meta = {
        "format": FORMAT, "version": VERSION, "settings": settings,
        "library": _library_spec(model.library_),
        "state_names": list(model.state_names_), "feature_names": list(model.feature_names_),
        "noise_variance": model.noise_variance_, "n_parameters": model.n_parameters_,
        "restored": [list(p) for p in m.restored], "n_trajectories": len(model.x_),
        "history": model.history_, "online": getattr(m, "track_mean", None) is not None,
        "generator_options_used": dataclasses.asdict(m.generator.options),
    }
    arrays = {"feature_scale": model.feature_scale_, "derivative_scale": model.derivative_scale_,
              "encoder_inputs": model.encoder_inputs_.cpu().numpy(), "times": model.times_}
    for k, (x, xd) in enumerate(zip(model.x_, model.x_dot_, strict=True)):
        arrays |= {f"x_{k}": x, f"x_dot_{k}": xd}
    for name, tensor in m.state_dict().items():
        arrays[f"weight:{name}"] = tensor.detach().cpu().numpy()
    if meta["online"]:
        arrays |= {"track_mean": m.track_mean.cpu().numpy(),
                   "track_std": m.track_std.cpu().numpy()}
    exact = model.assessment_
    arrays |= {"exact_mean": exact.mean, "exact_sd": exact.sd, "exact_lower": exact.lower,
               "exact_upper": exact.upper}
    meta["doubts"] = list(exact.doubts)
    meta["doubt_kinds"] = [d.kind for d in as_doubts(exact.doubts)]
    write(path, json.dumps(meta, default=float), arrays)


def read_model(meta, arrays) -> DynamicSINDy:
    """Rebuild a DynamicSINDy from a file's contents (see :func:`latentsindy.load`)."""
    s = meta["settings"]
    est = DynamicSINDy(None, generator=s["generator"], generator_options=s["generator_options"],
                       training=s["training"], structure=s.get("structure", "generator"),
                       support=s["support"], time_varying=s["time_varying"], verbose=False,
                       seed=int(s["seed"]))
    weights = {k[len("weight:"):]: torch.as_tensor(v) for k, v in arrays.items()
               if k.startswith("weight:")}
    if "pin_mask" not in weights:  # version 1: nothing was pinned
        weights["pin_mask"] = torch.zeros_like(weights["support"], dtype=torch.bool)
        weights["pin_value"] = torch.zeros_like(weights["constants"])
    inputs = torch.as_tensor(arrays["encoder_inputs"], dtype=torch.float32)
    support = weights["support"].bool()
    sequential = generator_class(est.generator).sequential
    torch.manual_seed(0)  # construction draws initial weights, all overwritten below
    gen = build_generator(est.generator, inputs.shape[1], support.numel(),
                          meta.get("generator_options_used", est.generator_options))
    gen.allocate(inputs.shape[2], sample_positions(arrays["times"], "cpu"))
    if meta["version"] < 3 and hasattr(gen, "encoder_points"):
        gen.encoder_points = None  # its encoder was trained on every sample
    cls = SequentialCoefficientModel if sequential else CoefficientModel
    model = cls(gen, torch.zeros(support.shape), support, weights["time_varying"])
    model.load_state_dict(weights, strict=True)
    model.restored = [tuple(p) for p in meta["restored"]]
    if meta["online"]:
        model.track_mean = torch.as_tensor(arrays["track_mean"])
        model.track_std = torch.as_tensor(arrays["track_std"])
    model.eval()
    n = int(meta["n_trajectories"])
    est.x_ = [arrays[f"x_{k}"] for k in range(n)]
    est.x_dot_ = [arrays[f"x_dot_{k}"] for k in range(n)]
    est.state_names_ = tuple(str(v) for v in meta["state_names"])
    est.feature_names_ = tuple(str(v) for v in meta["feature_names"])
    est.library = est.library_ = _library(meta["library"], est.x_, est.state_names_)
    est.feature_scale_, est.derivative_scale_ = arrays["feature_scale"], arrays["derivative_scale"]
    est.noise_variance_ = float(meta["noise_variance"])
    est.encoder_inputs_, est.times_ = inputs, arrays["times"]
    est.support_ = support.numpy().copy()
    est.time_varying_ = weights["time_varying"].numpy().astype(bool) & est.support_
    est.n_parameters_ = int(meta["n_parameters"])
    est.generator_options_ = gen.options
    est.restored_terms_ = [(est.state_names_[i], est.feature_names_[j]) for i, j in model.restored]
    est.history_ = meta["history"]
    est.assessment_ = None  # version 1: no exact model (band: mean +- 2 std)
    if "exact_mean" in arrays:
        est.assessment_ = Assessment(arrays["exact_mean"], arrays["exact_sd"],
                                     arrays["exact_lower"], arrays["exact_upper"],
                                     read_doubts(meta["doubts"], meta.get("doubt_kinds")))
    est.doubts_ = () if est.assessment_ is None else est.assessment_.doubts
    est.model_ = model
    return est
