"""Score a discovered closed system against the truth, in the discovered variables.

latentsindy reports a hidden state as a coefficient of the observed equations (``h``
*is* the coefficient of term ``f`` in ``d s/dt``) or as the rate of another hidden
state. Both are functions of the true hidden variables, so the true system can be
rewritten exactly in the discovered variables (a change of variables in sympy, with
symbolic parameters, so structural zeros stay exact). Then equation by equation: extra
and missing terms, and the relative error of every true coefficient.
"""

from __future__ import annotations

import numpy as np
import sympy as sp


def definitions(result):
    """Each hidden state as ("coef", state, feature) or ("rate", k): the rate of hidden
    state k."""
    states = getattr(result, "hidden_states", None)
    if states is None:  # results without structured hidden states
        return [("coef", s, f) for s, f in result.hidden_terms]
    out = []
    for h in states:
        if h.rate_of is not None:
            out.append(("rate", [g.name for g in states].index(h.rate_of)))
        else:
            out.append(("coef", *h.terms[0]))
    return out


def _feature(name, symbols):
    expr = sp.Integer(1)
    if name == "1":
        return expr
    for part in name.split(" "):
        base, _, power = part.partition("^")
        expr *= symbols[base] ** int(power or 1)
    return expr


def truth_in_variables(draw, defs, hidden_names):
    """The true closed system in the observed states and the discovered hidden states
    (sympy, numeric coefficients), or None when the definitions do not map onto the
    true hidden variables (wrong structure)."""
    rhs, hidden = draw.truth["rhs"], draw.truth["hidden"]
    obs = {n: sp.Symbol(n, real=True) for n in draw.observed_names}
    obs_syms = list(obs.values())
    phis = []
    for d in defs:
        if d[0] == "coef":
            _, state, feature = d
            if state not in obs:
                return None
            poly = sp.Poly(sp.expand(rhs[obs[state]]), *obs_syms)
            mono = sp.Poly(_feature(feature, obs), *obs_syms).monoms()[0]
            phi = poly.as_dict().get(mono, sp.Integer(0))
        else:
            if d[1] >= len(phis):
                return None
            base = phis[d[1]]
            phi = sum(sp.diff(base, z) * rhs[z] for z in hidden)
        phis.append(sp.expand(phi))
    if len(phis) != len(hidden):
        return None
    us = [sp.Symbol(n, real=True) for n in hidden_names]
    sol = sp.solve([u - phi for u, phi in zip(us, phis, strict=True)], hidden, dict=True)
    if len(sol) != 1 or any(z not in sol[0] for z in hidden):
        return None
    sol = sol[0]
    out = {}
    for name, sym in obs.items():
        out[name] = rhs[sym].subs(sol)
    for name, phi in zip(hidden_names, phis, strict=True):
        rate = sum(sp.diff(phi, z) * rhs[z] for z in hidden) + sum(
            sp.diff(phi, x) * rhs[x] for x in obs_syms)
        out[name] = rate.subs(sol)
    return out


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


def r2_hidden(hidden, truth):
    """R^2 of every true hidden variable from the discovered ones (best affine map); min."""
    design = np.column_stack([hidden, np.ones(len(hidden))])
    coef, *_ = np.linalg.lstsq(design, truth, rcond=None)
    resid = truth - design @ coef
    r2 = 1 - np.sum(resid**2, axis=0) / np.sum((truth - truth.mean(axis=0)) ** 2, axis=0)
    return float(np.min(r2))


def score(result, draw):
    """Metrics of one discover_hidden result against its draw."""
    out = score_structure(result, draw)
    out["r2"] = r2_hidden(np.asarray(result.hidden), draw.hidden_true)
    return out


def score_structure(result, draw):
    """The number of hidden states, extra and missing terms, the largest relative error
    of the hidden and of the observed equations' coefficients."""
    defs = definitions(result)
    hidden_names = list(result.hidden_names)
    n_true = len(draw.truth["hidden"])
    out = {"n_hidden": len(hidden_names), "n_hidden_true": n_true}
    truth = truth_in_variables(draw, defs, hidden_names) if len(defs) == n_true else None
    if truth is None:
        out.update(exact=False, extra=np.nan, missing=np.nan, error=np.inf,
                   observed_error=np.inf)
        return out
    symbols = [sp.Symbol(n, real=True) for n in list(draw.observed_names) + hidden_names]
    rep = compare(result.rhs, truth, list(draw.observed_names) + hidden_names, symbols,
                  draw.truth["values"])
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
    defs = _natural(draw)
    rhs, hidden = draw.truth["rhs"], draw.truth["hidden"]
    obs_syms = [sp.Symbol(n, real=True) for n in draw.observed_names]
    phis = []
    for d in defs:
        if d[0] == "coef":
            obs = dict(zip(draw.observed_names, obs_syms, strict=True))
            poly = sp.Poly(sp.expand(rhs[obs[d[1]]]), *obs_syms)
            mono = sp.Poly(_feature(d[2], obs), *obs_syms).monoms()[0]
            phis.append(poly.as_dict()[mono])
        else:
            phis.append(sum(sp.diff(phis[d[1]], z) * rhs[z] for z in hidden))
    values = draw.truth["values"]
    args = hidden + obs_syms
    data = np.column_stack([draw.hidden_true, draw.observed_clean])
    cols = [np.broadcast_to(sp.lambdify(args, phi.subs(values), "numpy")(*data.T),
                            (len(data),)) for phi in phis]
    return np.column_stack(cols), hidden_names
