"""A nested system folded back: one hidden state whose law has a higher power.

A nested winner (:mod:`.nested`) holds a second hidden state ``h1``, the time-varying
coefficient of a term in ``h0``'s law. ``h1`` may be a variable of its own (Lorenz seen
through x: ``h1 = sigma (rho - z)``), or it may stand in for a function of the other
states that the closure library lacks. Rayleigh's oscillator seen through x
(``vdot = -x + mu (v - v^3)``) needs ``v^3``, one degree above the default closure; at 1%
noise (draw 4 of the benchmark's fresh batch) it came back confident as a nested system
with ``h1`` the coefficient of ``h0`` in ``dh0/dt`` (``h1`` about ``mu (1 - v^2)``), nine
parameters, held-out 1.03 +- 0.03. Every check passed: the nested law is a fine
approximation, and nothing in the search said that a single hidden state with a cubic
law explains the data as well.

:func:`folded_score` asks exactly that. It keeps the winner's observed equations
(which hold ``h0`` alone), drops ``h1``, and gives ``h0`` a law with every monomial of
the observed states and ``h0`` up to one degree above the closure library's,
started from a least-squares fit of ``h0``'s fitted rate along the fitted trajectories;
the system is refined by integration on the same data (and must join across its
segments, as every candidate) and scored on held-out segments. When it scores within
the winner's band, the data cannot tell a second hidden variable from a higher power
of the first: a doubt (:func:`folded_doubts`), not a verdict, since such a law lies
outside the search (as in :mod:`.beyond`). On Lorenz seen through x (whose second hidden
state is real) no cubic law in (x, h0) follows the data
(``tests/stage_two/test_folded.py``).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import pysindy as ps
import sympy as sp

from ..._core.doubt import Doubt
from ..context import TIE
from ..fit.field import ParametricSystem
from ..fit.held_out import cross_validate
from ..fit.refine import Problem
from ..fit.shooting import BlowUp


@dataclass(frozen=True)
class Folded:
    """One hidden state with a law of degree ``degree`` in place of a nested pair."""

    score: float  # held-out misfit, noise variances
    score_se: float
    degree: int
    size: int  # free coefficients plus the hidden initial value of each recording
    system: ParametricSystem


def folded_score(verdict, closure_library) -> Folded | None:
    """The nested ``verdict``'s system folded into one hidden state whose law holds
    every monomial up to one degree above ``closure_library``'s (a pysindy
    ``PolynomialLibrary``), refined on the verdict's data and scored; None when the
    verdict is not a scored nested system, the closure library is not polynomial, the
    observed equations hold the nested state, or the folded system cannot be fitted."""
    if not (verdict.scored and verdict.proposal.nested):  # (unscored: nothing to compare)
        return None
    system = verdict.system
    n_obs = system.n_observed
    if len(system.state_names) != n_obs + 2:
        return None
    symbols = system.symbols
    kept, nested = symbols[:n_obs + 1], symbols[n_obs + 1]
    used = system.free | (system.coef != 0)
    observed_features = [f for c, f in enumerate(system.features) if used[:n_obs, c].any()]
    if any(nested in sp.sympify(f).free_symbols for f in observed_features):
        return None
    if not isinstance(closure_library, ps.PolynomialLibrary):
        return None
    degree = int(closure_library.degree) + 1
    hidden_features = [sp.Mul(*combo) for k in range(degree + 1)
                       for combo in itertools.combinations_with_replacement(kept, k)]
    trajectories = verdict.problem.trajectories(verdict.fit)
    if any(not np.all(np.isfinite(tr)) for tr in trajectories):
        return None
    try:
        law = _rate_law(system, trajectories, hidden_features, kept)
    except np.linalg.LinAlgError:
        return None
    if law is None:
        return None
    features = tuple(dict.fromkeys([*observed_features, *hidden_features]))
    coef = np.zeros((n_obs + 1, len(features)))
    free = np.zeros_like(coef, dtype=bool)
    for c, f in enumerate(system.features):
        if f in observed_features:
            coef[:n_obs, features.index(f)] = system.coef[:n_obs, c]
            free[:n_obs, features.index(f)] = system.free[:n_obs, c]
    for f, value in zip(hidden_features, law, strict=True):
        coef[n_obs, features.index(f)], free[n_obs, features.index(f)] = value, True
    folded = ParametricSystem(tuple(system.state_names[:n_obs + 1]), n_obs, features, coef,
                              free)
    guesses = [tr[:, :n_obs + 1] for tr in trajectories]
    try:
        data = verdict.problem
        problem = Problem(folded, data.times, data.observed, guesses, data.options)
        fit = problem.fit(folded)
        if not problem.joins(fit):  # not a trajectory of its system, as in the judge
            return None
        score, score_se, _ = cross_validate(problem, fit)
    except (BlowUp, np.linalg.LinAlgError):
        return None
    if not np.isfinite(score):
        return None
    return Folded(score, score_se, degree, fit.system.n_parameters(len(problem.groups)),
                  fit.system)


def _rate_law(system, trajectories, features, kept):
    """Least-squares coefficients of ``features`` (in the states ``kept``) for the rate
    of the last kept state along ``trajectories`` (its law in ``system``); None when
    the columns are degenerate."""
    rate = sp.lambdify(system.symbols, system.rhs()[system.state_names[len(kept) - 1]])
    columns = sp.lambdify(kept, list(features))
    states = np.vstack(trajectories)
    target = np.broadcast_to(rate(*states.T), (len(states),))
    design = np.column_stack([np.broadcast_to(np.asarray(v, float), (len(states),))
                              for v in columns(*states[:, :len(kept)].T)])
    norms = np.linalg.norm(design, axis=0)
    if (np.any(norms == 0) or not np.all(np.isfinite(design))
            or not np.all(np.isfinite(target))):
        return None
    values, *_ = np.linalg.lstsq(design / norms, target, rcond=None)
    return values / norms


def folded_doubts(folded: Folded | None, score, score_se, size, names) -> tuple[str, ...]:
    """A doubt when the folded system scores within the chosen system's band: its
    ``score`` plus one standard error ``score_se``, or ``judge.TIE`` when that is less
    (noise-free data); ``names`` are the displayed names of the chosen system's two
    hidden states."""
    if folded is None or not folded.score <= max(score + score_se, TIE):
        return ()
    parent, nested = names
    return (Doubt("folded law",
            f"one hidden state ({parent}) whose law has terms up to degree {folded.degree} "
            f"reproduces held-out data at least as well as this system with two (score "
            f"{folded.score:.3g} +- {folded.score_se:.2g} against {score:.3g} +- "
            f"{score_se:.2g}; {folded.size} parameters against {size}): {nested} may stand "
            f"for a power of {parent} that the closure library lacks rather than a "
            f"variable of its own; try closure_library=ps.PolynomialLibrary(degree="
            f"{folded.degree}) and compare"),)
