"""Candidate libraries: any pysindy feature library, evaluated and named consistently."""

from __future__ import annotations

import copy

import numpy as np
import pysindy as ps
import sympy as sp
from sympy.parsing.sympy_parser import (
    convert_xor,
    implicit_multiplication_application,
    parse_expr,
    standard_transformations,
)

_TRANSFORMS = standard_transformations + (implicit_multiplication_application, convert_xor)


def check_library(library, what: str = "library"):
    """Return a fresh copy of a pysindy library (so the user's object is never mutated);
    ``what`` names the argument in the error."""
    if library is None:
        return ps.PolynomialLibrary(degree=2)
    base = ps.feature_library.base.BaseFeatureLibrary
    if isinstance(library, type) and issubclass(library, base):
        raise TypeError(f"{what} must be a pysindy feature library object; got the class "
                        f"{library.__name__} itself: call it, e.g. "
                        f"{library.__name__}() with its settings.")
    if not isinstance(library, base):
        raise TypeError(
            f"{what} must be a pysindy feature library (e.g. ps.PolynomialLibrary(degree=2)); "
            f"got {type(library).__name__}."
        )
    return copy.deepcopy(library)


def fit_library(library, trajectories, state_names):
    """Fit ``library`` and return (Theta per trajectory, feature names)."""
    library.fit([np.asarray(x) for x in trajectories])
    names = list(library.get_feature_names(input_features=list(state_names)))
    if len(names) == 0:
        raise ValueError(
            "The library is empty: it produced no candidate functions for "
            f"{len(state_names)} state(s). Use e.g. ps.PolynomialLibrary(degree=2)."
        )
    thetas = evaluate_library(library, trajectories)
    return thetas, names


def evaluate_library(library, trajectories):
    out = library.transform([np.asarray(x) for x in trajectories])
    return [np.asarray(o, dtype=float) for o in out]


def state_symbols(state_names):
    return [sp.Symbol(n, real=True) for n in state_names]


def feature_expressions(library, feature_names, state_names):
    """Sympy expression of each library feature in the state symbols.

    Polynomial libraries are built from their ``powers_`` (exact structure);
    other libraries from their feature names, with the state names bound to our own
    symbols so names such as ``E``, ``I`` or ``beta`` stay plain symbols.
    """
    symbols = state_symbols(state_names)
    if isinstance(library, ps.PolynomialLibrary) and hasattr(library, "powers_"):
        return [sp.Mul(*[s**int(p) for s, p in zip(symbols, row, strict=True)])
                for row in library.powers_]
    local = {str(s): s for s in symbols}
    exprs = []
    for name in feature_names:
        try:
            exprs.append(parse_expr(name, local_dict=local, transformations=_TRANSFORMS))
        except Exception as err:  # noqa: BLE001 - report the offending name
            raise ValueError(
                f"Cannot turn the library feature name {name!r} into a sympy expression ({err}). "
                "Give CustomLibrary sympy-parseable function_names, e.g. lambda x: f'exp({x})'."
            ) from None
    return exprs
