"""`HiddenDiscovery`: the closed system found by `discover_hidden`, and its checks."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import sympy as sp

from ._results import CoefficientSeries
from ._simulate import Simulation, integrate
from ._symbolic import VectorField

_FORMAT = "latentsindy.HiddenDiscovery/1"


@dataclass(frozen=True)
class HiddenComparison:
    """How well inferred hidden states match known ones, up to an affine map.

    Attributes
    ----------
    r2 : ndarray, shape (n_true,)
        R^2 of each true hidden variable predicted affinely from the inferred ones.
    scale : ndarray, shape (n_hidden, n_true)
    offset : ndarray, shape (n_true,)
        The map: ``true ~ hidden @ scale + offset``.
    """

    r2: np.ndarray
    scale: np.ndarray
    offset: np.ndarray


@dataclass(frozen=True)
class HiddenDiscovery:
    """Observed plus hidden states and the closed ODE that governs them.

    Attributes
    ----------
    times : ndarray (first trajectory) ; all_times : list of ndarray
    observed : ndarray (n_times, n_observed), first trajectory
    hidden : ndarray (n_times, n_hidden), first trajectory, in physical units
    hidden_std : ndarray (n_times, n_hidden), posterior std of the hidden states
    observed_names, hidden_names, state_names : tuple of str
    hidden_terms : tuple of (state, feature)
        The stage-one coefficients that became hidden states, in order.
    rhs : dict of str -> sympy expression
        Time derivative of each state, in Symbols named after the states.
    sindy : pysindy.SINDy or None
        The fitted closure model (None after :func:`load`).
    coefficients : CoefficientSeries
        Stage-one result (first trajectory).
    """

    times: np.ndarray
    observed: np.ndarray
    hidden: np.ndarray
    hidden_std: np.ndarray
    observed_names: tuple[str, ...]
    hidden_names: tuple[str, ...]
    hidden_terms: tuple[tuple[str, str], ...]
    rhs: dict
    sindy: object
    coefficients: CoefficientSeries
    all_times: list = field(repr=False)
    all_observed: list = field(repr=False)
    all_hidden: list = field(repr=False)
    initial_state: np.ndarray = field(repr=False, default=None)
    closure_candidates: list = field(repr=False, default_factory=list)

    @classmethod
    def build(cls, *, times, observed, hidden, hidden_std, observed_names, hidden_names,
              hidden_terms, rhs, sindy, coefficients, initial_state, closure_candidates=()):
        return cls(times[0], observed[0], hidden[0], hidden_std[0], tuple(observed_names),
                   tuple(hidden_names), tuple(tuple(p) for p in hidden_terms), dict(rhs), sindy,
                   coefficients, list(times), list(observed), list(hidden),
                   np.asarray(initial_state, dtype=float), list(closure_candidates))

    # ----------------------------------------------------------- views
    @property
    def state_names(self) -> tuple[str, ...]:
        return self.observed_names + self.hidden_names

    @property
    def symbols(self) -> list[sp.Symbol]:
        return [sp.Symbol(n, real=True) for n in self.state_names]

    @property
    def equations(self) -> list[sp.Eq]:
        """``d state/dt = rhs`` as sympy equations, for display."""
        tt = sp.Symbol("t")
        return [sp.Eq(sp.Derivative(sp.Function(n)(tt), tt), self.rhs[n])
                for n in self.state_names]

    @property
    def states(self) -> np.ndarray:
        """Observed and hidden states side by side (first trajectory)."""
        return np.hstack([self.observed, self.hidden])

    def vector_field(self) -> VectorField:
        """The closed vector field ``f(t, y)`` for numpy arrays or torch tensors."""
        return VectorField(self.symbols, [self.rhs[n] for n in self.state_names])

    # ----------------------------------------------------------- checks
    def simulate(self, t=None, x0=None, *, max_steps=20_000) -> Simulation:
        """Integrate the closed system with torchdiffeq (dopri5, finite step budget).

        ``x0`` defaults to the first observed (as smoothed by the differentiator, so
        measurement noise does not set the start) plus hidden state; a blow-up or an
        exhausted budget is reported in the result's ``status``, never a hang.
        """
        t = self.times if t is None else np.asarray(t, dtype=float)
        x0 = self.initial_state if x0 is None else np.asarray(x0, dtype=float)
        if x0.shape != (len(self.state_names),):
            raise ValueError(f"x0 must have shape ({len(self.state_names)},) for states "
                             f"{list(self.state_names)}; got shape {x0.shape}.")
        bound = 1e3 * max(1.0, float(np.max(np.abs(self.states))))
        return integrate(self.vector_field(), t, x0, self.state_names, bound=bound,
                         max_steps=max_steps)

    def compare_hidden(self, true_hidden) -> HiddenComparison:
        """R^2 of known hidden variables against the inferred ones after the best affine
        map (first trajectory)."""
        truth = np.asarray(true_hidden, dtype=float)
        truth = truth[:, None] if truth.ndim == 1 else truth
        if truth.shape[0] != self.hidden.shape[0]:
            raise ValueError(f"true_hidden has {truth.shape[0]} rows but the hidden states have "
                             f"{self.hidden.shape[0]}; pass the series on the same times.")
        design = np.hstack([self.hidden, np.ones((len(truth), 1))])
        coef, *_ = np.linalg.lstsq(design, truth, rcond=None)
        resid = truth - design @ coef
        r2 = 1 - np.sum(resid**2, axis=0) / np.sum((truth - truth.mean(axis=0)) ** 2, axis=0)
        return HiddenComparison(r2, coef[:-1], coef[-1])

    def to_latex(self) -> str:
        """The equations as a LaTeX ``aligned`` block."""
        lines = [rf"\dot{{{sp.latex(s)}}} &= {sp.latex(self.rhs[n])}"
                 for s, n in zip(self.symbols, self.state_names, strict=True)]
        return "\\begin{aligned}\n" + " \\\\\n".join(lines) + "\n\\end{aligned}"

    def summary(self) -> str:
        hid = ", ".join(f"{h} = coefficient of {f} in d{s}/dt"
                        for h, (s, f) in zip(self.hidden_names, self.hidden_terms, strict=True))
        lines = [f"Closed system: {len(self.observed_names)} observed + "
                 f"{len(self.hidden_names)} hidden state(s)", f"  hidden: {hid}"]
        lines += [f"  d{n}/dt = {_short(self.rhs[n])}" for n in self.state_names]
        return "\n".join(lines)

    # ----------------------------------------------------------- persistence
    def save(self, path) -> None:
        """Write equations, series and names to a ``.npz`` file (see :func:`load`)."""
        meta = {
            "format": _FORMAT,
            "observed_names": self.observed_names, "hidden_names": self.hidden_names,
            "hidden_terms": self.hidden_terms,
            "rhs": {n: sp.srepr(e) for n, e in self.rhs.items()},
            "state_names_stage_one": self.coefficients.state_names,
            "feature_names_stage_one": self.coefficients.feature_names,
            "n_trajectories": len(self.all_times),
            "initial_state": self.initial_state.tolist(),
        }
        arrays = {"meta": np.array(json.dumps(meta))}
        for k, (tk, xk, hk) in enumerate(zip(self.all_times, self.all_observed, self.all_hidden,
                                             strict=True)):
            arrays |= {f"times_{k}": tk, f"observed_{k}": xk, f"hidden_{k}": hk}
        c = self.coefficients
        arrays |= {"hidden_std": self.hidden_std, "coef_mean": c.mean, "coef_samples": c.samples,
                   "coef_support": c.support, "coef_time_varying": c.time_varying}
        with open(Path(path), "wb") as fh:
            np.savez_compressed(fh, **arrays)


def load(path) -> HiddenDiscovery:
    """Read a result written by ``HiddenDiscovery.save``.

    Only load files you trust: equations are stored as sympy ``srepr`` text and are
    rebuilt by sympy's parser. The pysindy model is not stored (``sindy`` is None).
    """
    with np.load(Path(path), allow_pickle=False) as data:
        meta = json.loads(str(data["meta"])) if "meta" in data.files else {}
        if meta.get("format") != _FORMAT:
            raise ValueError(f"{path} is not a saved HiddenDiscovery (format "
                             f"{meta.get('format')!r}, expected {_FORMAT!r}).")
        n = meta["n_trajectories"]
        times = [data[f"times_{k}"] for k in range(n)]
        observed = [data[f"observed_{k}"] for k in range(n)]
        hidden = [data[f"hidden_{k}"] for k in range(n)]
        coefs = CoefficientSeries.from_samples(
            times[0], data["coef_mean"], data["coef_samples"], meta["state_names_stage_one"],
            meta["feature_names_stage_one"], data["coef_support"], data["coef_time_varying"])
        hidden_std = data["hidden_std"]
    names = meta["observed_names"] + meta["hidden_names"]
    local = {n: sp.Symbol(n, real=True) for n in names}
    local |= {"Symbol": sp.Symbol, "Integer": sp.Integer, "Float": sp.Float, "Add": sp.Add,
              "Mul": sp.Mul, "Pow": sp.Pow, "Rational": sp.Rational}
    rhs = {n: sp.sympify(e, locals=local) for n, e in meta["rhs"].items()}
    rhs = {n: e.subs({sp.Symbol(s): local[s] for s in names}) for n, e in rhs.items()}
    return HiddenDiscovery.build(times=times, observed=observed, hidden=hidden,
                                 hidden_std=[hidden_std], observed_names=meta["observed_names"],
                                 hidden_names=meta["hidden_names"],
                                 hidden_terms=meta["hidden_terms"], rhs=rhs, sindy=None,
                                 coefficients=coefs, initial_state=meta["initial_state"])


def _short(expr):
    return str(expr.xreplace({f: sp.Float(float(f), 5) for f in expr.atoms(sp.Float)}))
