"""Score a discovered closed system against the truth, in the discovered variables.

latentsindy reports a hidden state as a coefficient of the observed equations (``h``
*is* the coefficient of term ``f`` in ``d s/dt``) or as the rate of another hidden
state. Both are functions of the true hidden variables, so the true system can be
rewritten exactly in the discovered variables (a change of variables in sympy, with
symbolic parameters, so structural zeros stay exact). Then equation by equation: extra
and missing terms, and the relative error of every true coefficient.
"""

from __future__ import annotations

from itertools import combinations

import numpy as np
import sympy as sp


def definitions(result):
    """Each hidden state as ("coef", state, feature, others) or ("rate", k): the rate of
    hidden state k. ``others`` are the terms of the found equation ``d state/dt`` as
    monomials in the definition's variables (a term with a hidden state that is not one of
    them counts as that state's carrier): the hidden state is the coefficient of
    ``feature`` in that equation as found, so it carries every true term divisible by
    ``feature`` that the found equation does not show on its own (Lorenz from x: ``dx/dt
    = h0`` defines ``h0 = sigma (y - x)``, ``dx/dt = h0 - sigma x`` defines ``h0 = sigma
    y``)."""
    states = getattr(result, "hidden_states", None)
    if states is None:  # results without structured hidden states
        return [("coef", s, f) for s, f in result.hidden_terms]
    out = []
    names = [h.name for h in states]
    for a, h in enumerate(states):
        if h.rate_of is not None:
            out.append(("rate", names.index(h.rate_of)))
            continue
        state, feature = h.terms[0]
        # the terms as monomials in the definition's variables: the observed states, and
        # in a hidden state's equation the hidden states defined before this one; a term
        # with another hidden state shows that state's carrier (dx/dt = h0 + x h1: h0
        # does not take in the x monomial, h1 carries it)
        hidden = names if state not in names else names[a:]
        strip = {sp.Symbol(n, real=True): sp.Integer(1) for n in hidden}
        others = tuple(f.xreplace(strip) for f in result.equation(state))
        out.append(("coef", state, feature, others))
    return out


def _feature(name, symbols):
    expr = sp.Integer(1)
    if name == "1":
        return expr
    for part in name.split(" "):
        base, _, power = part.partition("^")
        expr *= symbols[base] ** int(power or 1)
    return expr


def truth_in_variables(draw, defs, hidden_names, found=None, every=False):
    """The true closed system in the observed states and the discovered hidden states
    (sympy, numeric coefficients), or None when the definitions do not map onto the
    true hidden variables (wrong structure). A hidden state shifted by terms the truth
    lacks (:func:`_coefficient`) needs the ``found`` system (its right-hand sides) to
    fix the shifts."""
    rhs, hidden = draw.truth["rhs"], draw.truth["hidden"]
    obs_syms = [sp.Symbol(n, real=True) for n in draw.observed_names]
    phis = hidden_definitions(draw, defs, hidden_names, every)
    if phis is None or len(phis) != len(hidden):
        return None
    us = [sp.Symbol(n, real=True) for n in hidden_names]
    sol = sp.solve([u - phi for u, phi in zip(us, phis, strict=True)], hidden, dict=True)
    if len(sol) != 1 or any(z not in sol[0] for z in hidden):
        return None
    sol = sol[0]
    out = {n: rhs[x].subs(sol) for n, x in zip(draw.observed_names, obs_syms, strict=True)}
    for name, phi in zip(hidden_names, phis, strict=True):
        out[name] = _rate(phi, rhs, hidden + obs_syms).subs(sol)
    if _shifts(out.values()):
        symbols = obs_syms + us
        shifts = None if found is None else _solve_shifts(
            out, found, symbols, draw.truth["values"] if every else None)
        if shifts is None:
            return None
        out = {n: sp.expand(e.subs(shifts)) for n, e in out.items()}
    return out


def hidden_shift_terms(draw, defs, hidden_names):
    """The observed-state functions the hidden states were shifted by (``m / mono`` of
    :func:`_coefficient`), for the R^2 map; empty when none was."""
    phis = hidden_definitions(draw, defs, hidden_names) or []
    return observed_shift_terms(phis, [sp.Symbol(n, real=True) for n in draw.observed_names])


def observed_shift_terms(phis, observed):
    """The terms multiplying each shift in the hidden definitions ``phis`` that are
    functions of the ``observed`` symbols alone (a shift's coefficient can hold true
    hidden variables or other shifts when the found structure is wrong (Lorenz from x
    at 5-10% noise): those are not observed series, so not in the map)."""
    out = []
    for phi in phis:
        for shift in _shifts([phi]):
            term = sp.expand(-phi.coeff(shift))
            if term.free_symbols and term.free_symbols <= set(observed) and term not in out:
                out.append(term)
    return out


def hidden_definitions(draw, defs, hidden_names, every=False):
    """Each discovered hidden state as a function of the true variables (sympy), or None.
    A hidden state may be a coefficient of an earlier hidden state's equation (Lorenz
    from x: h1 is x's coefficient in dh0/dt): that equation is written in the observed
    states and the earlier hidden states first, the remaining true variables staying in
    the coefficients."""
    rhs, hidden = draw.truth["rhs"], draw.truth["hidden"]
    obs = {n: sp.Symbol(n, real=True) for n in draw.observed_names}
    obs_syms = list(obs.values())
    us = [sp.Symbol(n, real=True) for n in hidden_names]
    phis = []
    for d in defs:
        if d[0] == "rate":
            if d[1] >= len(phis):
                return None
            phis.append(sp.expand(_rate(phis[d[1]], rhs, hidden + obs_syms)))
            continue
        _, state, feature, *others = d
        if state in obs:
            variables = obs_syms
            poly = sp.Poly(sp.expand(rhs[obs[state]]), *obs_syms)
            mono = sp.Poly(_feature(feature, obs), *obs_syms).monoms()[0]
        elif state in hidden_names[:len(phis)]:
            known = _partial_solution(us[:len(phis)], phis, hidden)
            if known is None:
                return None
            rate = _rate(phis[hidden_names.index(state)], rhs, hidden + obs_syms)
            variables = obs_syms + us[:len(phis)]
            poly = sp.Poly(sp.expand(rate.subs(known)), *variables)
            names = {**obs, **dict(zip(hidden_names[:len(phis)], us, strict=False))}
            mono = sp.Poly(_feature(feature, names), *variables).monoms()[0]
        else:
            return None
        phis.append(_coefficient(poly, mono, others[0] if others else None, variables,
                                 every))
    return phis


SHIFT = "_shift"  # prefix of the unknown shifts (see _coefficient)


def _coefficient(poly, mono, others, variables, every=False):
    """The coefficient of monomial ``mono`` in ``poly``; with ``others`` (the found
    equation's terms beside it), plus every term divisible by ``mono`` that is not one
    of them, divided by it, and minus ``s_k m / mono`` for every term ``m`` beside it
    that ``mono`` divides and the truth lacks: the hidden state gave that term to the
    equation (Van der Pol found as ``dx/dt = h + mu x - mu x^3 / 3``: ``h = y - s_0 x -
    s_1 x^3``). The shifts ``s_k`` are unknowns, fixed later by the found structure
    (:func:`_solve_shifts`). With ``every``, a shift for every such term the found
    equation shows, the truth's own included: the hidden state may be shifted by a term
    the truth has, in the gauge where a term of its law vanishes (Lorenz seen through x
    and z: ``h0 = sigma y + s x`` with ``s`` the root of the quadratic that removes x
    from ``dh0/dt``)."""
    terms = poly.as_dict()
    if others is None:
        return sp.expand(terms.get(mono, sp.Integer(0)))
    shown = {sp.Poly(f, *variables).monoms()[0] for f in others
             if f.free_symbols <= set(variables)}
    out = sp.Integer(0)
    for m, c in terms.items():
        rest = tuple(a - b for a, b in zip(m, mono, strict=True))
        if min(rest) >= 0 and (m == mono or m not in shown):
            out += c * sp.Mul(*[v**e for v, e in zip(variables, rest, strict=True)])
    for m in sorted(shown):
        rest = tuple(a - b for a, b in zip(m, mono, strict=True))
        if min(rest) >= 0 and m != mono and (every or terms.get(m, 0) == 0):
            shift = sp.Dummy(SHIFT)
            out -= shift * sp.Mul(*[v**e for v, e in zip(variables, rest, strict=True)])
    return sp.expand(out)


def _shifts(exprs):
    return sorted({s for e in exprs for s in e.free_symbols
                   if isinstance(s, sp.Dummy) and s.name == SHIFT}, key=sp.default_sort_key)


def _solve_shifts(truth, found, symbols, values=None):
    """The shifts that make every term the found system lacks vanish from the truth in
    its variables (a linear or polynomial system in the shifts and the parameters), or
    None when no single solution does. With the parameters' ``values``, of several
    solutions the real one whose coefficients are nearest the found ones."""
    shifts = _shifts(truth.values())
    if not shifts:
        return {}
    eqs = []
    for name, expr in truth.items():
        try:
            have = set(sp.Poly(sp.expand(found[name]), *symbols).monoms())
            terms = sp.Poly(sp.expand(expr), *symbols).as_dict().items()
        except sp.PolynomialError:  # the truth is no polynomial in these variables (1/x)
            return None
        for mono, coef in terms:
            if mono not in have:
                eqs.append(coef)
    sol = sp.solve(eqs, shifts, dict=True) if eqs else []
    sol = [x for x in sol if all(s in x for s in shifts)]
    if len(sol) > 1 and values is not None:
        sol = sorted((x for x in sol if all(complex(v.subs(values)).imag == 0
                                            for v in x.values())),
                     key=lambda x: _distance(truth, found, symbols, x, values))[:1]
    return sol[0] if len(sol) == 1 else None


def _distance(truth, found, symbols, shifts, values):
    """Largest relative difference of the found coefficients from the truth's with
    ``shifts`` (numeric), over the truth's terms."""
    worst = 0.0
    for name, expr in truth.items():
        t = sp.Poly(sp.expand(expr.subs(shifts).subs(values)), *symbols).as_dict()
        f = sp.Poly(sp.expand(found[name]), *symbols).as_dict()
        for mono, coef in t.items():
            c = complex(coef)
            if abs(c) > 1e-9:
                worst = max(worst, abs(complex(f.get(mono, 0.0)) / c - 1))
    return worst


def _rate(phi, rhs, variables):
    """d phi/dt along the true system."""
    return sum(sp.diff(phi, v) * rhs[v] for v in variables)


def _partial_solution(us, phis, hidden):
    """Solve ``us = phis`` for as many true hidden variables as there are equations (the
    first subset with one solution), or None."""
    eqs = [u - phi for u, phi in zip(us, phis, strict=True)]
    for subset in combinations(hidden, len(eqs)):
        sol = sp.solve(eqs, list(subset), dict=True)
        if len(sol) == 1 and all(z in sol[0] for z in subset):
            return sol[0]
    return None


def _monomials(expr, symbols, values=None):
    """{exponents: coefficient} of a polynomial; with ``values``, coefficients that are
    structurally zero (in the symbolic parameters) are dropped before substituting."""
    poly = sp.Poly(sp.expand(expr), *symbols)
    out = {}
    for mono, coef in poly.as_dict().items():
        if values is not None:
            coef = sp.simplify(coef)
            if coef == 0:
                continue
            coef = coef.subs(values)
        value = float(coef)
        if value != 0.0 or values is not None:
            out[mono] = value
    return out


def compare(found, truth, names, symbols, values):
    """Per equation: (extra, missing, max relative error over the true terms)."""
    report = {}
    for n in names:
        f = _monomials(found[n], symbols)
        t = _monomials(truth[n], symbols, values)
        extra = sorted(set(f) - set(t))
        missing = sorted(set(t) - set(f))
        errs = [abs(f[m] / t[m] - 1) if m in f else np.inf for m in t]
        report[n] = (len(extra), len(missing), max(errs) if errs else 0.0)
    return report


def r2_hidden(hidden, truth, observed=None):
    """R^2 of every true hidden variable from the discovered ones (best affine map, with
    the observed states in it when given); min."""
    extra = [] if observed is None else [observed]
    design = np.column_stack([hidden, *extra, np.ones(len(hidden))])
    coef, *_ = np.linalg.lstsq(design, truth, rcond=None)
    resid = truth - design @ coef
    r2 = 1 - np.sum(resid**2, axis=0) / np.sum((truth - truth.mean(axis=0)) ** 2, axis=0)
    return float(np.min(r2))


def score(result, draw):
    """Metrics of one discover_hidden result against its draw."""
    out = score_structure(result, draw)
    observed = draw.observed if draw.with_observed else None
    if observed is not None:  # and the terms a hidden state was shifted by
        shifted = (hidden_shift_terms(draw, definitions(result), list(result.hidden_names))
                   if len(result.hidden_names) == len(draw.truth["hidden"]) else [])
        symbols = [sp.Symbol(n, real=True) for n in draw.observed_names]
        observed = np.column_stack([observed] + [
            np.broadcast_to(sp.lambdify(symbols, term, "numpy")(*observed.T),
                            (len(observed),)) for term in shifted])
    out["r2"] = r2_hidden(np.asarray(result.hidden), draw.hidden_true, observed)
    return out


def score_structure(result, draw):
    """The number of hidden states, extra and missing terms, the largest relative error
    of the hidden and of the observed equations' coefficients."""
    defs = definitions(result)
    hidden_names = list(result.hidden_names)
    n_true = len(draw.truth["hidden"])
    out = {"n_hidden": len(hidden_names), "n_hidden_true": n_true}
    out.update(_structure(result, draw, defs, hidden_names, every=False))
    if not out["exact"] and len(defs) == n_true:
        # the hidden state may be shifted by a term the truth has, in the gauge where
        # a term of its law vanishes (see _coefficient)
        shifted = _structure(result, draw, defs, hidden_names, every=True)
        if shifted["exact"]:
            out.update(shifted)
    return out


def _structure(result, draw, defs, hidden_names, every):
    out = {}
    truth = (truth_in_variables(draw, defs, hidden_names, result.rhs, every)
             if len(defs) == len(draw.truth["hidden"]) else None)
    if truth is None:
        out.update(exact=False, extra=np.nan, missing=np.nan, error=np.inf,
                   observed_error=np.inf)
        return out
    symbols = [sp.Symbol(n, real=True) for n in list(draw.observed_names) + hidden_names]
    try:
        rep = compare(result.rhs, truth, list(draw.observed_names) + hidden_names, symbols,
                      draw.truth["values"])
    except sp.PolynomialError:  # the truth is no polynomial in these variables (1/x)
        out.update(exact=False, extra=np.nan, missing=np.nan, error=np.inf,
                   observed_error=np.inf)
        return out
    extra = sum(r[0] for r in rep.values())
    missing = sum(r[1] for r in rep.values())
    out.update(exact=extra == 0 and missing == 0, extra=extra, missing=missing,
               error=max(rep[h][2] for h in hidden_names),
               observed_error=max(rep[n][2] for n in draw.observed_names))
    return out


def score_hidden_equations(found, draw, hidden_names):
    """Extra, missing and max error of hidden equations alone (baselines and oracle),
    in the natural variables of the draw."""
    truth = truth_in_variables(draw, _natural(draw), hidden_names)
    symbols = [sp.Symbol(n, real=True) for n in list(draw.observed_names) + hidden_names]
    rep = compare(found, truth, hidden_names, symbols, draw.truth["values"])
    return (sum(r[0] for r in rep.values()), sum(r[1] for r in rep.values()),
            max(r[2] for r in rep.values()))


def _natural(draw):
    out = []
    for k, d in enumerate(draw.natural):
        out.append(("rate", k - 1) if d == "rate" else ("coef", *d))
    return out


def natural_series(draw):
    """The true hidden series in the natural variables (the coefficients and rates that
    latentsindy should report), noise-free."""
    hidden_names = [f"h{k}" for k in range(len(draw.natural))]
    phis = hidden_definitions(draw, _natural(draw), hidden_names)
    hidden = draw.truth["hidden"]
    obs_syms = [sp.Symbol(n, real=True) for n in draw.observed_names]
    values = draw.truth["values"]
    args = hidden + obs_syms
    data = np.column_stack([draw.hidden_true, draw.observed_clean])
    cols = [np.broadcast_to(sp.lambdify(args, phi.subs(values), "numpy")(*data.T),
                            (len(data),)) for phi in phis]
    return np.column_stack(cols), hidden_names
