"""Saving and loading results: equations stored as structure, never as code.

Every expression is written as a tree of whitelisted node types (sums, products,
powers, numbers, state symbols and a few elementary functions) and rebuilt node by
node from that whitelist: nothing read from a file is parsed or evaluated as Python or
sympy text. A file that is not a result, or holds anything outside the whitelist, is
refused with a ValueError naming the file and the problem.
"""

from __future__ import annotations

import json
import math
import zipfile
from pathlib import Path

import numpy as np
import sympy as sp

from ._discovery import Alternative, HiddenDiscovery, HiddenState, Refinement, Term
from ._persist_model import FORMAT as MODEL_FORMAT
from ._persist_model import VERSION as MODEL_VERSION
from ._persist_model import load_model, read_any
from ._results import CoefficientSeries

FORMAT = "latentsindy.HiddenDiscovery"
VERSION = 3  # 3 added ``doubts``; version 2 files still load (no doubts)
READABLE = (2, 3)
_FUNCTIONS = {f.__name__: f for f in (sp.sin, sp.cos, sp.tan, sp.exp, sp.log, sp.tanh,
                                      sp.sinh, sp.cosh, sp.Abs)}


class _Refused(ValueError):
    pass


def to_tree(expr):
    """A JSON-able tree of ``expr`` (see the module docstring)."""
    expr = sp.sympify(expr)
    if isinstance(expr, sp.Symbol):
        return ["Symbol", expr.name]
    if isinstance(expr, sp.Integer):
        return ["Integer", str(int(expr))]
    if isinstance(expr, sp.Rational):
        return ["Rational", str(expr.p), str(expr.q)]
    if isinstance(expr, sp.Float):
        return ["Float", repr(float(expr))]
    if isinstance(expr, sp.Add | sp.Mul):
        return [type(expr).__name__, [to_tree(a) for a in expr.args]]
    if isinstance(expr, sp.Pow):
        return ["Pow", to_tree(expr.base), to_tree(expr.exp)]
    name = type(expr).__name__
    if name in _FUNCTIONS:
        return ["Function", name, [to_tree(a) for a in expr.args]]
    raise ValueError(f"Cannot store the expression {expr} (node {name}); only sums, "
                     f"products, powers, numbers, states and {sorted(_FUNCTIONS)}.")


def from_tree(tree, symbols):
    """Rebuild an expression from :func:`to_tree` output; ``symbols`` maps the allowed
    state names to their symbols."""
    if not isinstance(tree, list) or not tree or not isinstance(tree[0], str):
        raise _Refused(f"malformed expression node {str(tree)[:60]!r}")
    kind = tree[0]
    try:
        if kind == "Symbol":
            if tree[1] not in symbols:
                raise _Refused(f"unknown symbol {str(tree[1])[:40]!r} in an expression")
            return symbols[tree[1]]
        if kind == "Integer":
            return sp.Integer(int(_digits(tree[1])))
        if kind == "Rational":
            return sp.Rational(int(_digits(tree[1])), int(_digits(tree[2])))
        if kind == "Float":
            return sp.Float(_number(tree[1]))
        if kind == "Add":
            return sp.Add(*[from_tree(a, symbols) for a in tree[1]])
        if kind == "Mul":
            return sp.Mul(*[from_tree(a, symbols) for a in tree[1]])
        if kind == "Pow":
            return sp.Pow(from_tree(tree[1], symbols), from_tree(tree[2], symbols))
        if kind == "Function" and tree[1] in _FUNCTIONS:
            return _FUNCTIONS[tree[1]](*[from_tree(a, symbols) for a in tree[2]])
    except (IndexError, TypeError) as err:
        raise _Refused(f"malformed {kind!r} node ({err})") from None
    raise _Refused(f"expression node {str(kind)[:40]!r} is not allowed")


def _digits(text):
    if not isinstance(text, str) or not text.lstrip("-").isdigit() or len(text) > 400:
        raise _Refused(f"not an integer: {str(text)[:40]!r}")
    return text


def _number(text):
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise _Refused(f"not a number: {str(text)[:40]!r}") from None
    return value


def _hidden_state(h):
    return {"name": h.name, "terms": [list(t) for t in h.terms], "rate_of": h.rate_of}


def _alternative(a):
    return {"description": a.description, "rhs": {n: to_tree(e) for n, e in a.rhs.items()},
            "hidden_states": [_hidden_state(h) for h in a.hidden_states], "score": a.score,
            "score_se": a.score_se, "size": a.size, "status": a.status}


def save(result: HiddenDiscovery, path) -> None:
    """Write ``result`` to ``path`` (``.npz``; arrays plus one JSON document)."""
    meta = {
        "format": FORMAT, "version": VERSION,
        "observed_names": list(result.observed_names), "hidden_names": list(result.hidden_names),
        "hidden_states": [_hidden_state(h) for h in result.hidden_states],
        "terms": [{"state": t.state, "feature": to_tree(t.feature), "value": t.value,
                   "stderr": t.stderr, "fixed": t.fixed} for t in result.terms],
        "score": result.score, "score_se": result.score_se, "notes": list(result.notes),
        "doubts": list(result.doubts),
        "alternatives": [_alternative(a) for a in result.alternatives],
        "uncertain": [_alternative(a) for a in result.uncertain],
        "refinement": None if result.refinement is None else vars(result.refinement),
        "stage_one_states": list(result.coefficients.state_names),
        "stage_one_features": list(result.coefficients.feature_names),
        "n_trajectories": len(result.all_times),
    }
    arrays = {"meta": np.array(json.dumps(meta)), "hidden_std": result.hidden_std,
              "initial_state": np.asarray(result.initial_state, dtype=float)}
    for k in range(len(result.all_times)):
        arrays |= {f"times_{k}": result.all_times[k], f"observed_{k}": result.all_observed[k],
                   f"hidden_{k}": result.all_hidden[k],
                   f"hidden_initial_{k}": result.hidden_initial[k]}
    c = result.coefficients
    arrays |= {"coef_mean": c.mean, "coef_samples": c.samples, "coef_support": c.support,
               "coef_time_varying": c.time_varying}
    with open(Path(path), "wb") as fh:
        np.savez_compressed(fh, **arrays)


def load(path):
    """Read a file written by ``HiddenDiscovery.save`` or ``DynamicSINDy.save``.

    Returns the HiddenDiscovery or the fitted DynamicSINDy. Equations are rebuilt from
    their stored structure (a whitelist of node types and the result's own state
    names), networks from their settings with the stored weights; nothing in the file
    is unpickled or evaluated. A file that is neither, or is damaged, is refused with a
    ValueError that names it.
    """
    path = Path(path)
    try:
        meta, arrays = read_any(path)
        if meta.get("format") == MODEL_FORMAT:
            if meta.get("version") != MODEL_VERSION:
                raise _Refused(f"DynamicSINDy file version {meta.get('version')!r}; this "
                               f"latentsindy reads version {MODEL_VERSION}")
            return load_model(meta, arrays, path)
        if meta.get("format") != FORMAT or meta.get("version") not in READABLE:
            raise _Refused(f"not a saved HiddenDiscovery or DynamicSINDy (format "
                           f"{meta.get('format')!r}, version {meta.get('version')!r}; "
                           f"expected {FORMAT!r}, versions "
                           f"{', '.join(map(str, READABLE))}, or {MODEL_FORMAT!r})")
        return _build(meta, arrays)
    except _Refused as err:
        raise ValueError(f"{path} cannot be loaded: {err}.") from None
    except (KeyError, TypeError, AttributeError, ValueError, OSError, RuntimeError,
            zipfile.BadZipFile) as err:
        if str(err).startswith(f"{path} cannot be loaded"):
            raise  # read_any's message already names the file and the problem
        detail = " ".join(str(err).split())  # one line
        raise ValueError(f"{path} cannot be loaded: missing or malformed entry "
                         f"({type(err).__name__}: {detail}).") from None


def _names(values, what):
    if not isinstance(values, list) or not all(isinstance(v, str) and v.isidentifier()
                                               for v in values):
        raise _Refused(f"{what} must be a list of identifiers")
    return tuple(values)


def _state(d, symbols_names):
    h = HiddenState(str(d["name"]), tuple(tuple(map(str, t)) for t in d["terms"]),
                    None if d["rate_of"] is None else str(d["rate_of"]))
    if h.name not in symbols_names:
        raise _Refused(f"hidden state {h.name[:40]!r} is not among the result's states")
    return h


def _build(meta, arrays):
    observed = _names(meta["observed_names"], "observed_names")
    hidden = _names(meta["hidden_names"], "hidden_names")
    names = observed + hidden
    symbols = {n: sp.Symbol(n, real=True) for n in names}
    terms = []
    for t in meta["terms"]:
        if t["state"] not in symbols:
            raise _Refused(f"a term belongs to unknown state {str(t['state'])[:40]!r}")
        terms.append(Term(t["state"], from_tree(t["feature"], symbols), _number(t["value"]),
                          _number(t["stderr"]) if t["stderr"] is not None else math.nan,
                          bool(t["fixed"])))

    def alternative(a):
        alt_names = set(names) | {h["name"] for h in a["hidden_states"]}
        alt_symbols = {n: sp.Symbol(n, real=True) for n in alt_names if n.isidentifier()}
        return Alternative(str(a["description"]),
                           {str(n): from_tree(e, alt_symbols) for n, e in a["rhs"].items()},
                           tuple(_state(h, alt_symbols) for h in a["hidden_states"]),
                           _number(a["score"]), _number(a["score_se"]), int(a["size"]),
                           str(a["status"]))

    n = int(meta["n_trajectories"])
    times = [arrays[f"times_{k}"] for k in range(n)]
    observed_series = [arrays[f"observed_{k}"] for k in range(n)]
    hidden_series = [arrays[f"hidden_{k}"] for k in range(n)]
    initial = [arrays[f"hidden_initial_{k}"] for k in range(n)]
    coefs = CoefficientSeries.from_samples(
        times[0], arrays["coef_mean"], arrays["coef_samples"],
        _names(meta["stage_one_states"], "stage_one_states"),
        [str(f) for f in meta["stage_one_features"]], arrays["coef_support"],
        arrays["coef_time_varying"])
    refinement = meta["refinement"]
    return HiddenDiscovery(
        times[0], observed_series[0], hidden_series[0], arrays["hidden_std"], observed, hidden,
        tuple(_state(h, symbols) for h in meta["hidden_states"]), tuple(terms), coefs,
        _number(meta["score"]), _number(meta["score_se"]),
        tuple(alternative(a) for a in meta["alternatives"]),
        tuple(alternative(a) for a in meta["uncertain"]),
        None if refinement is None else Refinement(**{k: refinement[k] for k in (
            "misfit_before", "misfit_after", "continuity_gap", "n_segments", "iterations",
            "status")}),
        tuple(str(s) for s in meta["notes"]), times, observed_series, hidden_series, initial,
        arrays["initial_state"], _doubts(meta))


def _doubts(meta):
    if meta["version"] < 3:  # written before results carried their checks
        return ("saved by an older latentsindy (file version 2) that did not record the "
                "checks on the result; rerun discover_hidden to check it",)
    return tuple(str(s) for s in meta["doubts"])
