"""The parts of a :class:`~latentsindy.results.HiddenDiscovery`: what a hidden state is,
the terms of the closed system, the alternatives considered, how the system was refined,
and how inferred hidden states compare with known ones."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import sympy as sp


@dataclass(frozen=True)
class HiddenState:
    """What a hidden state is, in terms of the observed equations.

    Attributes
    ----------
    name : str
    terms : tuple of (equation, feature)
        The observed-equation terms whose coefficients move with this state. The
        state *is* the coefficient of the first one; the others read ``c + w * name``
        in the equations (one hidden variable seen through several terms).
    rate_of : str or None
        Set when the state is the time derivative of another hidden state (a hidden
        state that no coefficient shows, found because the first one's law needs it).
    """

    name: str
    terms: tuple = ()
    rate_of: str | None = None

    def describe(self) -> str:
        if self.rate_of is not None:
            return f"{self.name} = d{self.rate_of}/dt"
        (state, feature), *rest = self.terms
        text = f"{self.name} = coefficient of {feature} in d{state}/dt"
        if rest:
            text += " (also moves the coefficient" + ("s" if len(rest) > 1 else "") + " of " \
                + ", ".join(f"{f} in d{s}/dt" for s, f in rest) + ")"
        return text


@dataclass(frozen=True)
class Term:
    """One term of the closed system: ``value * feature`` in ``d state/dt``."""

    state: str
    feature: sp.Expr
    value: float
    stderr: float  # nan where not estimated (a definition, or refinement off)
    fixed: bool  # part of a hidden state's definition (value 1)


@dataclass(frozen=True)
class Alternative:
    """Another structure the judge considered.

    ``score`` is its held-out score when ``status`` is "scored"; for "rejected" (misfit
    far above the best), "blew up" and "does not join" (a hidden state jumps between
    integration segments, so the fit is no trajectory of the system) it is the in-sample
    misfit (noise variances); for "not refined" (``refine=False``) it is NaN. ``size``:
    its parameters, free coefficients plus hidden initial values (one set per
    recording), the count ranking weighs.
    """

    description: str
    rhs: dict
    hidden_states: tuple
    score: float
    score_se: float
    size: int
    status: str  # "scored", "rejected", "blew up", "does not join", "not refined"


@dataclass(frozen=True)
class Refinement:
    """How the closed system was fitted by integration (multiple shooting).

    ``misfit_before`` / ``misfit_after``: RMS of (model - data) / std(data) over the
    observed states, with the closure's coefficients and with the refined ones.
    """

    misfit_before: float
    misfit_after: float
    continuity_gap: float  # largest gap between segments, in noise units
    n_segments: int
    iterations: int
    status: str


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
    observed_scale : ndarray, shape (len(observed_terms), n_true), or None
        With ``with_observed=True``, the observed part of the map, one row per entry of
        ``observed_terms``.
    observed_terms : tuple of sympy expressions
        With ``with_observed=True``, what the map may add: the observed states, then
        the observed terms the hidden states absorb (see
        :meth:`HiddenDiscovery.compare_hidden`); empty otherwise.
    """

    r2: np.ndarray
    scale: np.ndarray
    offset: np.ndarray
    observed_scale: np.ndarray | None = None
    observed_terms: tuple = ()
