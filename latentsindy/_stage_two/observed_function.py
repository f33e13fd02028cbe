"""Hidden states that are functions of the observed states.

A closed system can carry a state ``h`` whose law is the time derivative, along the
system, of a polynomial ``F`` of the observed states: ``dh/dt = sum_i dF/dx_i dx_i/dt``.
Then ``h - F(x)`` is conserved, so ``h = F(x) + c`` is no hidden variable: it is how a
closure library writes a term it lacks. A damped Duffing oscillator seen through x,
with the default closure library of degree 2, came back confident with two hidden
states: ``dx/dt = h0``, ``dh0/dt = -delta h0 + x h1``, ``dh1/dt = -2 beta x h0``, where
``h1 = -beta x^2 - alpha`` stands for the ``x^3`` of the velocity's law.

:func:`observed_function` finds ``F`` exactly (the law's coefficients against those of
the derivatives of the observed monomials, solved by least squares and accepted only
when they match to rounding); :func:`reduced_system` substitutes ``h = F + c`` (``c``
the conserved quantity's mean along the fitted trajectories) for a nested state, so the
judge refits and scores the system with one hidden state fewer, like any restatement.
"""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import sympy as sp

from .field import polynomial_rows, system_from_rows

MAX_DEGREE = 4  # highest total degree of F tried
TOLERANCE = 1e-8  # relative mismatch of the law's coefficients accepted as rounding


def observed_function(system, state: int):
    """``F`` (a polynomial of the observed states without constant term) whose time
    derivative along ``system`` is the law of state ``state`` (a hidden one); None when
    there is none (or the law is zero: a constant, reported elsewhere)."""
    symbols = system.symbols
    observed = symbols[:system.n_observed]
    rhs = system.rhs()
    target = sp.expand(rhs[symbols[state].name])
    if target == 0 or not observed:
        return None
    monomials = [sp.Mul(*combo) for degree in range(1, MAX_DEGREE + 1)
                 for combo in itertools.combinations_with_replacement(observed, degree)]
    try:
        rates = [sp.Poly(sp.expand(sum(sp.diff(m, x) * rhs[x.name] for x in observed)),
                         *symbols).as_dict() for m in monomials]
        goal = sp.Poly(target, *symbols).as_dict()
    except sp.PolynomialError:
        return None
    keys = sorted(set(goal).union(*rates))
    a = np.array([[float(r.get(key, 0.0)) for r in rates] for key in keys])
    b = np.array([float(goal.get(key, 0.0)) for key in keys])
    coef = np.linalg.lstsq(a, b, rcond=None)[0]
    if np.linalg.norm(a @ coef - b) > TOLERANCE * np.linalg.norm(b):
        return None
    keep = np.abs(coef) > TOLERANCE * np.abs(coef).max()
    return sp.Add(*[sp.Float(c) * m for c, m, k in zip(coef, monomials, keep, strict=True)
                    if k])


def reduced_system(verdict):
    """The winner without its nested state where that state is a function of the
    observed states: (system, guesses) with ``F + c`` substituted (``c`` its
    conserved mean along the fitted trajectories), or None."""
    p, system = verdict.proposal, verdict.system
    if len(p.nested) != 1 or p.order != 1:
        return None
    child = len(system.state_names) - 1  # the nested state is the last one
    found = observed_function(system, child)
    if found is None:
        return None
    trajectories = verdict.problem.trajectories(verdict.fit)
    if not all(np.all(np.isfinite(tr)) for tr in trajectories):
        return None
    symbols = system.symbols
    n_obs = system.n_observed
    value = sp.lambdify(symbols[:n_obs], found, modules="numpy")
    c = float(np.mean(np.concatenate([
        tr[:, child] - np.broadcast_to(value(*tr[:, :n_obs].T), (len(tr),))
        for tr in trajectories])))
    names = system.state_names[:child]
    rhs = system.rhs()
    laws = {n: sp.expand(rhs[n].subs(symbols[child], found + sp.Float(c))) for n in names}
    rows = polynomial_rows(laws, names)
    if rows is None:
        return None
    reduced = system_from_rows(names, n_obs, rows, system, kept_rows=n_obs)
    guesses = [np.delete(tr, child, axis=1) for tr in trajectories]
    return reduced, guesses


def reduced_proposal(p, guesses, n_observed, name):
    """The proposal as the reduced system's origin: no nested state, its hidden series."""
    return replace(p, nested=(), hidden=[g[:, n_observed:] for g in guesses],
                   origin=p.origin + f", {name} as a function of the observed states")
