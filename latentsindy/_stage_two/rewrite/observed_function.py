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

A fitted law is rarely that exact: a weakly supported term (``0.0001 h0 h1`` in the
state's law, ``0.0005 x^3`` in the observed one) breaks the identity though the state
still follows ``F(x)`` along the data. Where no exact ``F`` exists,
:func:`trajectory_function` fits one along the fitted trajectories (least squares on the
observed monomials, the lowest degree that follows the state to ``NEAR`` of its spread)
and that ``F`` is substituted instead; the judge's score decides, as for any restatement,
whether the system without the state reproduces the data as well.
"""

from __future__ import annotations

import itertools

import numpy as np
import sympy as sp

from ..context import NEAR
from ..fit.field import polynomial_rows, system_from_rows

MAX_DEGREE = 4  # highest total degree of F tried
TOLERANCE = 1e-8  # relative mismatch of the law's coefficients accepted as rounding


def observed_function(system, state: int, over=None):
    """``F`` (a polynomial without constant term of the observed states, or of the
    states ``over``, indices that must not include ``state``) whose time derivative
    along ``system`` is the law of state ``state`` (a hidden one); None when there is
    none (or the law is zero: a constant, reported elsewhere)."""
    symbols = system.symbols
    over = range(system.n_observed) if over is None else over
    if state in over:
        raise ValueError(f"a state cannot be a function of itself (state {state}, over "
                         f"{list(over)})")
    observed = [symbols[i] for i in over]
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


def trajectory_function(trajectories, n_observed: int, state: int, symbols):
    """``F`` (a polynomial of the observed states with a constant) that state ``state``
    follows along ``trajectories`` to ``NEAR`` of its spread, of the lowest degree that
    does; None when no degree up to ``MAX_DEGREE`` does."""
    x = np.concatenate([tr[:, :n_observed] for tr in trajectories])
    h = np.concatenate([tr[:, state] for tr in trajectories])
    spread = float(np.std(h))
    if n_observed == 0 or not spread > 0 or not np.all(np.isfinite(x)):
        return None
    scale = np.maximum(np.std(x, axis=0), 1e-12)  # conditioning: monomials of x / scale
    u = x / scale
    combos, columns = [()], [np.ones(len(h))]
    for degree in range(1, MAX_DEGREE + 1):
        for combo in itertools.combinations_with_replacement(range(n_observed), degree):
            combos.append(combo)
            columns.append(np.prod(u[:, list(combo)], axis=1))
        a = np.column_stack(columns)
        coef = np.linalg.lstsq(a, h, rcond=None)[0]
        if np.sqrt(np.mean((h - a @ coef) ** 2)) <= NEAR * spread:
            return sp.Add(*[sp.Float(c / np.prod(scale[list(combo)]))
                            * sp.Mul(*[symbols[i] for i in combo])
                            for c, combo in zip(coef, combos, strict=True)])
    return None


def state_function(system, state: int):
    """``F`` (a polynomial of the observed states and of the other hidden states, no
    constant term, not using ``state``) whose time derivative along ``system`` is the
    law of hidden state ``state`` exactly; None when there is none.

    Then ``state - F`` is a first integral of the system: the state is no hidden
    variable of its own but a function of the others, and the system is a lifted form
    of a smaller one. Van der Pol seen through its velocity y came back as
    ``dy/dt = h0 + h1 y``, ``dh0/dt = -y``, ``dh1/dt = 2 mu h0 y``: ``h1 + mu h0^2`` is
    conserved, and ``h1 = mu (1 - h0^2)`` gives Van der Pol with one hidden state."""
    others = [i for i in range(len(system.state_names)) if i != state]
    return observed_function(system, state, over=others)


def function_reduced_system(verdict, state: int):
    """The winner without hidden state ``state`` where it is an exact function of the
    other states (:func:`state_function`): (system, guesses, candidates) with ``F + c``
    substituted (``c`` the conserved quantity's mean along the fitted trajectories), or
    None. ``candidates``: the lifted system's candidate terms in the other hidden laws
    that do not involve the state."""
    system = verdict.system
    if not system.n_observed <= state < len(system.state_names):
        return None
    found = state_function(system, state)  # symbolic and cheap: before integrating
    if found is None:
        return None
    trajectories = verdict.problem.trajectories(verdict.fit)
    if not all(np.all(np.isfinite(tr)) for tr in trajectories):
        return None
    return _substituted(verdict, state, found, trajectories, exact=True)


def reduced_system(verdict):
    """The winner without its nested state where that state is a function of the
    observed states: (system, guesses, candidates) with ``F + c`` substituted (``F``
    exact and ``c`` the conserved quantity's mean along the fitted trajectories, or else
    ``F`` the :func:`trajectory_function` with its constant), ``candidates`` the terms
    term selection may add (the lifted system's in the hidden laws, bar those of the
    state); or None."""
    p, system = verdict.proposal, verdict.system
    if len(p.nested) != 1 or p.order != 1:
        return None
    child = len(system.state_names) - 1  # the nested state is the last one
    trajectories = verdict.problem.trajectories(verdict.fit)
    if not all(np.all(np.isfinite(tr)) for tr in trajectories):
        return None
    found = observed_function(system, child)
    if found is None:
        found = trajectory_function(trajectories, system.n_observed, child, system.symbols)
        if found is None:
            return None
        return _substituted(verdict, child, found, trajectories, exact=False)
    return _substituted(verdict, child, found, trajectories, exact=True)


def _substituted(verdict, state, found, trajectories, exact):
    """(system, guesses, candidates): ``verdict``'s system with ``state = found`` (plus,
    where ``exact``, the conserved quantity's mean along ``trajectories``) substituted
    into the other laws; None if they are no polynomials."""
    system = verdict.system
    symbols = system.symbols
    n_obs = system.n_observed
    if exact:
        value = sp.lambdify(symbols, found, modules="numpy")
        found = found + sp.Float(float(np.mean(np.concatenate([
            tr[:, state] - np.broadcast_to(value(*tr.T), (len(tr),))
            for tr in trajectories]))))
    names = system.state_names[:state] + system.state_names[state + 1:]
    rhs = system.rhs()
    laws = {n: sp.expand(rhs[n].subs(symbols[state], found)) for n in names}
    rows = polynomial_rows(laws, names)
    if rows is None:
        return None
    # the terms term selection could add to the lifted system's hidden laws, less those
    # of the state (the observed laws stay as chosen: a term added there could only
    # restate a hidden state, shifted by a function of the observed states)
    pool = verdict.candidates
    cells = [] if pool is None else [
        (i, f) for i in range(n_obs, len(system.state_names)) if i != state
        for f, allowed in zip(system.features, pool[i], strict=True)
        if allowed and symbols[state] not in f.free_symbols]
    leading = tuple(dict.fromkeys(f for _, f in cells))
    reduced = system_from_rows(names, n_obs, rows, system, leading=leading, kept_rows=n_obs)
    candidates = np.zeros_like(reduced.free)
    for i, f in cells:
        candidates[i - (i > state), reduced.features.index(f)] = True
    guesses = [np.delete(tr, state, axis=1) for tr in trajectories]
    return reduced, guesses, candidates & ~reduced.free


def reduced_proposal(p, guesses, n_observed, name):
    """The proposal as the reduced system's origin: no nested state, its hidden series."""
    return p.derived(f", {name} as a function of the observed states", nested=(),
                     hidden=[g[:, n_observed:] for g in guesses])
