"""Pieces of nested discovery (a hidden state inside another's equation)."""

import sympy as sp

from latentsindy._stage_two.nested import monomial_name


def test_monomial_names_follow_the_library_convention():
    x, h0 = sp.symbols("x h0", real=True)
    assert monomial_name(x * h0**2, [x, h0]) == "x h0^2"
    assert monomial_name(sp.Integer(1), [x, h0]) == "1"
    assert monomial_name(x, [x, h0]) == "x"
