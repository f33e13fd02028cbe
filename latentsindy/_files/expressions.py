"""Equations in files: sympy expressions as trees of whitelisted node types.

Every expression is written as a tree of sums, products, powers, numbers, state symbols
and a few elementary functions, and rebuilt node by node from that whitelist: nothing
read from a file is parsed or evaluated as Python or sympy text.
"""

from __future__ import annotations

import sympy as sp

from .container import Refused

_FUNCTIONS = {f.__name__: f for f in (sp.sin, sp.cos, sp.tan, sp.exp, sp.log, sp.tanh,
                                      sp.sinh, sp.cosh, sp.Abs)}


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
        raise Refused(f"malformed expression node {str(tree)[:60]!r}")
    kind = tree[0]
    try:
        if kind == "Symbol":
            if tree[1] not in symbols:
                raise Refused(f"unknown symbol {str(tree[1])[:40]!r} in an expression")
            return symbols[tree[1]]
        if kind == "Integer":
            return sp.Integer(int(digits(tree[1])))
        if kind == "Rational":
            return sp.Rational(int(digits(tree[1])), int(digits(tree[2])))
        if kind == "Float":
            return sp.Float(number(tree[1]))
        if kind == "Add":
            return sp.Add(*[from_tree(a, symbols) for a in tree[1]])
        if kind == "Mul":
            return sp.Mul(*[from_tree(a, symbols) for a in tree[1]])
        if kind == "Pow":
            return sp.Pow(from_tree(tree[1], symbols), from_tree(tree[2], symbols))
        if kind == "Function" and tree[1] in _FUNCTIONS:
            return _FUNCTIONS[tree[1]](*[from_tree(a, symbols) for a in tree[2]])
    except (IndexError, TypeError) as err:
        raise Refused(f"malformed {kind!r} node ({err})") from None
    raise Refused(f"expression node {str(kind)[:40]!r} is not allowed")


def digits(text):
    if not isinstance(text, str) or not text.lstrip("-").isdigit() or len(text) > 400:
        raise Refused(f"not an integer: {str(text)[:40]!r}")
    return text


def number(text):
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise Refused(f"not a number: {str(text)[:40]!r}") from None
    return value
