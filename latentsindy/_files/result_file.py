"""The result file: a :class:`HiddenDiscovery` as arrays plus one JSON document.

Equations are stored as expression trees (:mod:`.expressions`), never as code. Reading
checks every entry; a file that holds anything else is refused (:class:`.container.Refused`,
turned into a ValueError naming the file by :func:`latentsindy.load`).
"""

from __future__ import annotations

import json
import math

import numpy as np
import sympy as sp

from .._core import saving
from .._core.doubt import read_doubts
from .._core.recordings import DataUse
from .._stage_one.coefficients import CoefficientSeries
from .._stage_two.result import HiddenDiscovery
from .._stage_two.result_parts import Alternative, HiddenState, Refinement, Term
from .container import Refused, write
from .expressions import from_tree, number, to_tree

FORMAT = "latentsindy.HiddenDiscovery"
VERSION = 5  # 3 added ``doubts``, 4 ``data_use``, 5 stage one's band and doubts
READABLE = (2, 3, 4, 5)


def _hidden_state(h):
    return {"name": h.name, "terms": [list(t) for t in h.terms], "rate_of": h.rate_of}


def _alternative(a):
    return {"description": a.description, "rhs": {n: to_tree(e) for n, e in a.rhs.items()},
            "hidden_states": [_hidden_state(h) for h in a.hidden_states], "score": a.score,
            "score_se": a.score_se, "size": a.size, "status": a.status}


@saving.save.register
def save_result(result: HiddenDiscovery, path) -> None:
    """Write ``result`` to ``path`` (``.npz``; arrays plus one JSON document)."""
    meta = {
        "format": FORMAT, "version": VERSION,
        "observed_names": list(result.observed_names), "hidden_names": list(result.hidden_names),
        "hidden_states": [_hidden_state(h) for h in result.hidden_states],
        "terms": [{"state": t.state, "feature": to_tree(t.feature), "value": t.value,
                   "stderr": t.stderr, "fixed": t.fixed} for t in result.terms],
        "score": result.score, "score_se": result.score_se, "notes": list(result.notes),
        "doubts": list(result.doubts), "doubt_kinds": [d.kind for d in result.doubts],
        "alternatives": [_alternative(a) for a in result.alternatives],
        "uncertain": [_alternative(a) for a in result.uncertain],
        "refinement": None if result.refinement is None else vars(result.refinement),
        "stage_one_states": list(result.coefficients.state_names),
        "stage_one_features": list(result.coefficients.feature_names),
        "stage_one_doubts": list(result.coefficients.doubts),
        "stage_one_doubt_kinds": [d.kind for d in result.coefficients.doubts],
        "n_trajectories": len(result.all_times),
        "data_use": None if result.data_use is None else {
            "recordings": result.data_use.recordings, "segments": result.data_use.segments,
            "samples": result.data_use.samples, "missing_rows": result.data_use.missing_rows,
            "dropped": list(result.data_use.dropped),
            "sources": [list(s) for s in result.data_use.sources],
            "discounted": [list(s) for s in result.data_use.discounted]},
    }
    arrays = {"hidden_std": result.hidden_std,
              "initial_state": np.asarray(result.initial_state, dtype=float)}
    for k in range(len(result.all_times)):
        arrays |= {f"times_{k}": result.all_times[k], f"observed_{k}": result.all_observed[k],
                   f"hidden_{k}": result.all_hidden[k],
                   f"hidden_initial_{k}": result.hidden_initial[k]}
    c = result.coefficients
    arrays |= {"coef_times": c.times, "coef_mean": c.mean, "coef_samples": c.samples,
               "coef_support": c.support, "coef_time_varying": c.time_varying,
               "coef_lower": c.lower, "coef_upper": c.upper}
    write(path, json.dumps(meta), arrays)


def _names(values, what):
    if not isinstance(values, list) or not all(isinstance(v, str) and v.isidentifier()
                                               for v in values):
        raise Refused(f"{what} must be a list of identifiers")
    return tuple(values)


def _state(d, symbols_names):
    h = HiddenState(str(d["name"]), tuple(tuple(map(str, t)) for t in d["terms"]),
                    None if d["rate_of"] is None else str(d["rate_of"]))
    if h.name not in symbols_names:
        raise Refused(f"hidden state {h.name[:40]!r} is not among the result's states")
    return h


def read_result(meta, arrays) -> HiddenDiscovery:
    """Rebuild a result from a file's JSON document and arrays (checked entry by entry)."""
    observed = _names(meta["observed_names"], "observed_names")
    hidden = _names(meta["hidden_names"], "hidden_names")
    names = observed + hidden
    symbols = {n: sp.Symbol(n, real=True) for n in names}
    terms = []
    for t in meta["terms"]:
        if t["state"] not in symbols:
            raise Refused(f"a term belongs to unknown state {str(t['state'])[:40]!r}")
        terms.append(Term(t["state"], from_tree(t["feature"], symbols), number(t["value"]),
                          number(t["stderr"]) if t["stderr"] is not None else math.nan,
                          bool(t["fixed"])))

    def alternative(a):
        alt_names = set(names) | {h["name"] for h in a["hidden_states"]}
        alt_symbols = {n: sp.Symbol(n, real=True) for n in alt_names if n.isidentifier()}
        return Alternative(str(a["description"]),
                           {str(n): from_tree(e, alt_symbols) for n, e in a["rhs"].items()},
                           tuple(_state(h, alt_symbols) for h in a["hidden_states"]),
                           number(a["score"]), number(a["score_se"]), int(a["size"]),
                           str(a["status"]))

    n = int(meta["n_trajectories"])
    times = [arrays[f"times_{k}"] for k in range(n)]
    observed_series = [arrays[f"observed_{k}"] for k in range(n)]
    hidden_series = [arrays[f"hidden_{k}"] for k in range(n)]
    initial = [arrays[f"hidden_initial_{k}"] for k in range(n)]
    coef_times = arrays["coef_times"] if meta["version"] >= 4 else times[0]
    coefs = CoefficientSeries.from_samples(
        coef_times, arrays["coef_mean"], arrays["coef_samples"],
        _names(meta["stage_one_states"], "stage_one_states"),
        [str(f) for f in meta["stage_one_features"]], arrays["coef_support"],
        arrays["coef_time_varying"], lower=arrays.get("coef_lower"),
        upper=arrays.get("coef_upper"),
        doubts=read_doubts(meta.get("stage_one_doubts", []),
                           meta.get("stage_one_doubt_kinds")))
    refinement = meta["refinement"]
    return HiddenDiscovery(
        times[0], observed_series[0], hidden_series[0], arrays["hidden_std"], observed, hidden,
        tuple(_state(h, symbols) for h in meta["hidden_states"]), tuple(terms), coefs,
        number(meta["score"]), number(meta["score_se"]),
        tuple(alternative(a) for a in meta["alternatives"]),
        tuple(alternative(a) for a in meta["uncertain"]),
        None if refinement is None else Refinement(**{k: refinement[k] for k in (
            "misfit_before", "misfit_after", "continuity_gap", "n_segments", "iterations",
            "status")}),
        tuple(str(s) for s in meta["notes"]), times, observed_series, hidden_series, initial,
        arrays["initial_state"], _doubts(meta), _data_use(meta))


def _data_use(meta):
    d = meta.get("data_use") if meta["version"] >= 4 else None
    if d is None:
        return None
    return DataUse(int(d["recordings"]), int(d["segments"]), int(d["samples"]),
                   int(d["missing_rows"]), tuple(str(s) for s in d["dropped"]),
                   tuple(tuple(int(v) for v in s) for s in d["sources"]),
                   tuple((int(k), float(t)) for k, t in d.get("discounted", [])))


def _doubts(meta):
    if meta["version"] < 3:  # written before results carried their checks
        return ("saved by an older latentsindy (file version 2) that did not record the "
                "checks on the result; rerun discover_hidden to check it",)
    return read_doubts(meta["doubts"], meta.get("doubt_kinds"))
