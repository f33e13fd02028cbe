"""Doubts about the hidden states themselves: a state that is a function of the
observed ones, a state written twice, a state faster than the sampling resolves, and a
first integral that was not preferred."""

from __future__ import annotations

import math

import numpy as np
import sympy as sp
import torch

from ..._core.doubt import Doubt
from ..context import NEAR
from ..fit.field import FeatureMap
from ..rewrite.first_integral import integrated_system
from ..rewrite.gauge import partial_shift
from ..rewrite.observed_function import observed_function, state_function, trajectory_function

# The hidden states' own dynamics (the hidden-hidden block of the Jacobian) may not be
# faster than the data resolve: a state that relaxes (or turns) within one sampling step
# follows the others quasi-statically, so its law is not identified by the data. A
# typical (median over the samples) largest rate of that block times the typical step
# above this is a failed check (see ``unresolved_doubts``).
UNRESOLVED = 1.0


def first_integral_doubt(verdict, names):
    """A doubt when the winner's rate law has a first integral (:mod:`.first_integral`):
    the smaller first-order system with one constant was judged and not preferred, so
    the conserved quantity differs between recordings or segments, or the fit is not
    settled; either way the second hidden state is not shown to be dynamics."""
    if integrated_system(verdict) is None:
        return ()
    h, r = names[0], names[1]
    return (Doubt("first integral", f"d{r}/dt is the time derivative of a first-order law for {h} "
            f"(d{h}/dt = G({h}) + c, with c = {r} - G({h}) conserved), yet that smaller "
            "system was not preferred: c differs between recordings or segments, or the "
            f"fit is not settled; {r} may stand for a constant per recording rather than "
            "dynamics"),)


def observed_function_doubts(system, names_map):
    """A doubt per hidden state that is a function of the observed states
    (:mod:`.observed_function`): it is no hidden variable, only a way of writing terms
    the closure library lacks."""
    out = []
    several = len(system.state_names) - system.n_observed > 1
    for k in range(system.n_observed, len(system.state_names)):
        found = observed_function(system, k)
        other = state_function(system, k) if found is None and several else None
        expr = found if found is not None else other
        if expr is None:
            continue
        name = names_map.get(system.state_names[k], system.state_names[k])
        shown = _shown(expr, _user_symbols(system, names_map))
        if other is not None:
            out.append(Doubt("observed function",
                       f"{name} is a function of the other states, {name} = {shown} + "
                       f"constant (a first integral of the system): the system is a lifted "
                       f"form of one with a hidden state fewer, which did not reproduce the "
                       f"data as well when refitted"))
            continue
        out.append(Doubt("observed function",
                   f"{name} is a function of the observed states, {name} = {shown} + "
                   f"constant (its law is that function's time derivative along the "
                   f"system): not a hidden variable, but terms the closure library lacks; "
                   f"substituted, the system has one hidden state fewer (a closure_library "
                   f"with higher powers may find it)"))
    return tuple(out)


def partial_shift_doubts(system, names_map):
    """A doubt when one hidden state shifted by part of an observed term gives the same
    dynamics with fewer terms (:func:`..rewrite.gauge.partial_shift`): the state is a
    mix of a hidden and an observed variable, the mix is not fixed by the data (the
    extra terms lie along it), and the sparser form is the law to read."""
    found = partial_shift(system)
    if found is None:
        return ()
    h, shift, laws, before, after = found
    name = names_map.get(h.name, h.name)
    new = sp.Symbol(f"{name}'", real=True)
    old = _user_symbols(system, names_map)
    rename = old | {h: new}
    laws_text = "; ".join(f"d{rename[s]}/dt = {_shown(laws[s.name], rename)}"
                          for s in system.symbols)
    return (Doubt("partial shift",
                  f"{name} mixes a hidden variable with an observed one: in {new} = "
                  f"{_shown(h + shift, old)} the same dynamics have {after} terms instead of "
                  f"{before} ({laws_text}); the data do not fix the mix, so the extra terms "
                  f"are not determined. Read the shifted form: the same system with the "
                  f"fewest terms"),)


def _user_symbols(system, names_map):
    """The system's symbols -> symbols under the names the result shows."""
    return {s: sp.Symbol(names_map.get(s.name, s.name), real=True) for s in system.symbols}


def _shown(expr, symbols):
    """``expr`` as a doubt shows it: four significant digits, the result's names."""
    return expr.xreplace({f: sp.Float(f, 4) for f in expr.atoms(sp.Float)}).xreplace(symbols)


def unresolved_rate(system, trajectories, times):
    """The hidden states' typical own rate per sampling step: the median over the samples
    of the largest eigenvalue modulus of the Jacobian's hidden-hidden block, along the
    fitted trajectories, times the median step between samples; and the index of the
    hidden state whose row of that block is largest (the fastest). (nan, None) without
    hidden states or finite states."""
    n_obs, n = system.n_observed, len(system.state_names)
    if n == n_obs:
        return math.nan, None
    features = FeatureMap(system.features, system.symbols)
    rates, rows, steps = [], [], []
    for states, t in zip(trajectories, times, strict=True):
        states = np.asarray(states, dtype=float)
        states = states[np.isfinite(states).all(axis=1)]
        steps.append(np.diff(np.asarray(t, dtype=float)))
        if len(states) == 0:
            continue
        _, dphi = features(torch.as_tensor(states))
        block = np.einsum("tfs,if->tis", dphi.numpy(), system.coef)[:, n_obs:, n_obs:]
        block = block[np.isfinite(block).all(axis=(1, 2))]
        if len(block):
            rates.append(np.abs(np.linalg.eigvals(block)).max(axis=-1))
            rows.append(np.linalg.norm(block, axis=2))
    if not rates:
        return math.nan, None
    step = float(np.median(np.concatenate(steps)))
    fastest = int(np.argmax(np.median(np.concatenate(rows), axis=0)))
    return float(np.median(np.concatenate(rates))) * step, n_obs + fastest


def unresolved_doubts(system, trajectories, times, names_map):
    """A doubt when the hidden states' own dynamics are faster than the sampling
    (:func:`unresolved_rate` above ``UNRESOLVED``).

    Such a state is slaved to the others: within a step it settles where its law's
    fast term balances the rest, so a system with a hidden state fewer (or another law)
    describes the same data, and the fast coefficients are not determined. Seen on
    fresh systems at 1% noise: Chen's system (z hidden) came back three times in 10
    draws as z and its rate, the rate's law relaxing at 2.1-2.7 e-foldings per sampling
    step (the true z: 0.015), and Rikitake's dynamo once with a second hidden state
    relaxing at 33 per step, all confident and wrong. Over the discovery benchmark's
    default table (356 systems) and eight held-out families (160 calls) the largest
    value is 0.37, 0.23 among exact results (0.016 on the fresh batch); every value above
    1 seen was a wrong law. A true hidden rate near the sampling rate would not be
    identifiable from such data either.
    """
    per_step, fastest = unresolved_rate(system, trajectories, times)
    if not per_step > UNRESOLVED:
        return ()
    name = system.state_names[fastest]
    name = names_map.get(name, name)
    return (Doubt("unresolved",
            f"the hidden states' own dynamics are faster than the sampling: typically "
            f"{per_step:.3g} e-foldings (or radians) per sampling step, fastest in d{name}/dt, "
            f"so {name} follows the other states quasi-statically and its law is not "
            "determined by these data; a system with a hidden state fewer may describe "
            "them as well (try max_hidden, hidden_terms, or data sampled faster)"),)


def redundant_state_doubts(verdict, names_map, trajectories):
    """A doubt per hidden state that follows a polynomial of the other states along the
    fitted trajectories, to ``NEAR`` of its spread (:func:`.observed_function.
    trajectory_function`), where the winner has several first-order hidden states, none
    nested: it may be another state written again, not a variable of its own. Rikitake's
    dynamo seen through x and y came back with z twice (``h0 = z`` in dx/dt, ``h1 = z - A``
    in dy/dt, both laws ``1 - x y`` to the fit's precision), confident; the exact check
    (:func:`.observed_function.state_function`) misses it by the coefficients' noise.
    ``trajectories``: the winner's fitted states (``problem.trajectories(fit)``)."""
    p, system = verdict.proposal, verdict.system
    n_obs, n = system.n_observed, len(system.state_names)
    if p.nested or p.order != 1 or n - n_obs < 2 or not verdict.scored:
        return ()
    if not all(np.all(np.isfinite(tr)) for tr in trajectories):
        return ()
    symbols, out = system.symbols, []
    for k in range(n_obs, n):
        others = [i for i in range(n) if i != k]
        moved = [tr[:, others + [k]] for tr in trajectories]
        found = trajectory_function(moved, len(others), len(others),
                                    [symbols[i] for i in others] + [symbols[k]])
        if found is None:
            continue
        name = names_map.get(system.state_names[k], system.state_names[k])
        shown = found.xreplace({f: sp.Float(f, 4) for f in found.atoms(sp.Float)}
                               | {s: sp.Symbol(names_map.get(s.name, s.name), real=True)
                                  for s in symbols})
        out.append(Doubt("redundant state",
                   f"{name} follows the other states along the data ({name} = {shown} to "
                   f"{NEAR:.0%} of its spread): it may be another state written again, not "
                   "a hidden variable of its own; a system with one hidden state fewer may "
                   "describe the data as well"))
    return tuple(out)
