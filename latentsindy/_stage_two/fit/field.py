"""A closed system linear in its coefficients: ``dy_i/dt = sum_f coef[i, f] phi_f(y)``.

Features are sympy expressions in the state symbols (the observed library's features
times powers of hidden states, and the closure library's monomials). Monomials are
evaluated from their exponents (a few batched array operations for any number of
features, in numpy or torch); any other feature (Fourier, custom libraries) through
sympy's lambdify, in torch. Both give the features and their gradients, which the
refinement's sensitivity equations need.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp
import torch


@dataclass(frozen=True)
class ParametricSystem:
    """Structure and coefficients of a closed system.

    Attributes
    ----------
    state_names : tuple of str
        Observed states first, then hidden ones.
    n_observed : int
    features : tuple of sympy expressions
        Candidate functions of the states (one column each).
    coef : ndarray (n_states, n_features)
        Coefficients; zero outside the structure.
    free : ndarray of bool (n_states, n_features)
        Coefficients that are estimated; the others stay as given (the hidden states'
        scale: ``h`` *is* the coefficient of its term, so that coefficient is 1).
    """

    state_names: tuple[str, ...]
    n_observed: int
    features: tuple
    coef: np.ndarray
    free: np.ndarray

    @property
    def symbols(self) -> list[sp.Symbol]:
        return [sp.Symbol(n, real=True) for n in self.state_names]

    @property
    def n_free(self) -> int:
        return int(self.free.sum())

    def n_parameters(self, recordings: int = 1) -> int:
        """Free coefficients plus the hidden initial values, one set per recording
        (each recording's hidden states start where its data put them)."""
        return self.n_free + (len(self.state_names) - self.n_observed) * max(recordings, 1)

    @property
    def n_terms(self) -> int:
        return int(((self.coef != 0) | self.free).sum())

    def free_values(self) -> np.ndarray:
        return self.coef[self.free]

    def with_free(self, values) -> ParametricSystem:
        coef = self.coef.copy()
        coef[self.free] = np.asarray(values, dtype=float)
        return ParametricSystem(self.state_names, self.n_observed, self.features, coef,
                                self.free)

    def rhs(self) -> dict:
        """Sympy right-hand sides built from the coefficients and the features."""
        out = {}
        for i, name in enumerate(self.state_names):
            expr = sp.Integer(0)
            for c, f in zip(self.coef[i], self.features, strict=True):
                if c != 0:
                    expr += sp.Float(float(c)) * f
            out[name] = expr
        return out


_TINY = 1e-12  # relative size below which a coefficient of a derived law is zero


def polynomial_rows(laws, state_names):
    """Each state's law (a polynomial sympy expression, ``laws[name]``) as
    ``{monomial: coefficient}``, coefficients below ``_TINY`` of the row's largest left
    out; None if a law is not a polynomial in the states."""
    symbols = [sp.Symbol(n, real=True) for n in state_names]
    rows = []
    for name in state_names:
        try:
            terms = sp.Poly(laws[name], *symbols).terms()
        except sp.PolynomialError:
            return None
        scale = max((abs(float(c)) for _, c in terms), default=0.0)
        rows.append({sp.Mul(*[s**e for s, e in zip(symbols, powers, strict=True)]): float(c)
                     for powers, c in terms if abs(float(c)) > _TINY * scale})
    return rows


def system_from_rows(state_names, n_observed, rows, template, *, leading=(), kept_rows):
    """A ParametricSystem from ``polynomial_rows``: features ``leading`` first, then
    the others in sympy's order; every coefficient is free except, in the first
    ``kept_rows`` rows, those ``template`` holds fixed and nonzero (a hidden state's
    scale stays the coefficient of its term)."""
    old = {f: c for c, f in enumerate(template.features)}
    features = list(leading) + sorted({f for row in rows for f in row} - set(leading),
                                      key=sp.default_sort_key)
    coef = np.zeros((len(rows), len(features)))
    free = np.zeros_like(coef, dtype=bool)
    for i, row in enumerate(rows):
        for f, c in row.items():
            col = features.index(f)
            coef[i, col] = c
            fixed = (i < kept_rows and f in old and not template.free[i, old[f]]
                     and template.coef[i, old[f]] != 0)
            free[i, col] = not fixed
    return ParametricSystem(tuple(state_names), n_observed, tuple(features), coef, free)


class FeatureMap:
    """Features phi(y) and their gradients for batches of states, in torch."""

    def __init__(self, features, symbols):
        symbols = list(symbols)
        self.n_states = len(symbols)
        self._cache = {}
        self.exponents = _exponents(features, symbols)
        if self.exponents is None:
            grads = [[sp.diff(f, s) for s in symbols] for f in features]
            self._values = sp.lambdify(symbols, list(features), modules="torch")
            self._grads = sp.lambdify(symbols, [g for row in grads for g in row],
                                      modules="torch")
            self.n_features = len(features)
        else:
            self.n_features = self.exponents.shape[0]
            self.degree = int(self.exponents.max(initial=0))
            self.basis, self.values_table, self.gradients_table = _monomial_tables(
                self.exponents)
            self._flat_gradients = self.gradients_table.reshape(len(self.basis), -1)
            self._flat = (self.basis + (self.degree + 1) * np.arange(self.n_states)).ravel()

    def __call__(self, y: torch.Tensor, gradients: bool = True):
        """``phi`` (..., F) and, if asked, ``dphi`` (..., F, n)."""
        if self.exponents is None:
            return self._lambdified(y, gradients)
        mono = self.monomials(y)
        values, grads = self.tables(y)
        phi = mono @ values
        if not gradients:
            return phi, None
        return phi, (mono @ grads).reshape(*y.shape[:-1], self.n_features, self.n_states)

    def tables(self, like):
        """``values_table`` (M, F) and ``gradients_table`` flattened to (M, F * n), as
        numpy arrays for a numpy ``like``, else as tensors on ``like``'s device and dtype
        (made once per device and dtype)."""
        if isinstance(like, np.ndarray):
            return self.values_table, self._flat_gradients
        key = (like.device, like.dtype)
        if key not in self._cache:
            on = dict(dtype=like.dtype, device=like.device)
            self._cache[key] = (torch.as_tensor(self.values_table, **on),
                                torch.as_tensor(self._flat_gradients, **on))
        return self._cache[key]

    def monomials(self, y):
        """The monomials (..., M) of ``basis`` at ``y`` (polynomial features only; a
        numpy array or a tensor, the result alike): the features are ``monomials @
        values_table`` and their gradients ``monomials @ gradients_table``, so a field
        that is linear in its coefficients and its Jacobian come from one matrix
        product."""
        lead = y.shape[:-1]
        if isinstance(y, np.ndarray):
            powers = np.empty((*y.shape, self.degree + 1))
            powers[..., 0] = 1.0
            for d in range(self.degree):
                np.multiply(powers[..., d], y, out=powers[..., d + 1])
        else:
            powers = [torch.ones_like(y)]
            for _ in range(self.degree):
                powers.append(powers[-1] * y)
            powers = torch.stack(powers, -1)
        picked = powers.reshape(*lead, -1)[..., self._flat_index(y)]  # (..., M * n)
        return picked.reshape(*lead, len(self.basis), self.n_states).prod(-1)

    def _flat_index(self, y):
        if isinstance(y, np.ndarray):
            return self._flat
        key = ("flat", y.device)
        if key not in self._cache:
            self._cache[key] = torch.as_tensor(self._flat, device=y.device)
        return self._cache[key]

    def _lambdified(self, y, gradients):
        cols = torch.unbind(y, dim=-1)
        shape = y.shape[:-1]
        phi = torch.stack([_full(v, shape, y) for v in self._values(*cols)], dim=-1)
        if not gradients:
            return phi, None
        flat = [_full(v, shape, y) for v in self._grads(*cols)]
        dphi = torch.stack(flat, dim=-1).reshape(*shape, self.n_features, self.n_states)
        return phi, dphi


def _full(value, shape, like):
    if torch.is_tensor(value):
        return value.expand(shape)
    return torch.full(shape, float(value), dtype=like.dtype, device=like.device)


def _monomial_tables(exponents):
    """The monomials that the features and their gradients are made of, as an exponent
    matrix (M, n), and the tables (M, F) and (M, F, n) that combine them into the
    features and their gradients (a gradient of a monomial is an integer times a
    monomial of lower degree)."""
    n_features, n_states = exponents.shape
    basis, where = [], {}

    def index(e):
        e = tuple(int(v) for v in e)
        if e not in where:
            where[e] = len(basis)
            basis.append(e)
        return where[e]

    entries = [(index(e), f) for f, e in enumerate(exponents)]
    grads = []
    for f, e in enumerate(exponents):
        for s in range(n_states):
            if e[s] > 0:
                lower = np.array(e)
                lower[s] -= 1
                grads.append((index(lower), f, s, float(e[s])))
    values = np.zeros((len(basis), n_features))
    for m, f in entries:
        values[m, f] = 1.0
    gradients = np.zeros((len(basis), n_features, n_states))
    for m, f, s, c in grads:
        gradients[m, f, s] = c
    return np.array(basis, dtype=np.int64).reshape(-1, n_states), values, gradients


def _exponents(features, symbols):
    """Exponent matrix (F, n) when every feature is a monomial with coefficient 1."""
    rows = []
    for f in features:
        f = sp.sympify(f)
        if not f.free_symbols <= set(symbols):
            return None
        try:
            poly = sp.Poly(f, *symbols)
        except sp.PolynomialError:
            return None
        terms = poly.terms()
        if len(terms) != 1 or terms[0][1] != 1:
            return None
        rows.append(terms[0][0])
    return np.array(rows, dtype=np.int64).reshape(len(rows), len(symbols))
