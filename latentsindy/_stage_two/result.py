"""`HiddenDiscovery`: the closed system found by `discover_hidden`, and its checks."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import sympy as sp

from .._core import saving
from .._core.doubt import as_doubts
from .._core.recordings import DataUse
from .._core.simulate import Simulation, integrate
from .._core.symbolic import VectorField
from .._stage_one.coefficients import CoefficientSeries
from .figures import plot_discovery
from .result_parts import HiddenComparison, Refinement
from .summary import summary_text


@dataclass(frozen=True, repr=False)
class HiddenDiscovery:
    """Observed plus hidden states and the closed ODE that governs them.

    Attributes
    ----------
    times, observed, hidden : ndarray
        First trajectory (the longest segment, the one stage one was fitted on): times,
        observed states (n_times, n_observed), hidden states
        (n_times, n_hidden). With refinement on, ``hidden`` is the closed system's
        trajectory fitted to the data; the stage-two estimate is ``hidden_initial``.
    hidden_std : ndarray (n_times, n_hidden)
        Standard deviation of the hidden states (from the refinement's covariance;
        the generator's posterior std without refinement; NaN where unknown).
    observed_names, hidden_names : tuple of str
    hidden_states : tuple of HiddenState
    terms : tuple of Term
        The closed system, term by term, with standard errors.
    score, score_se : float
        Held-out misfit (noise variances; about 1 when the system reproduces data it
        was not fitted to down to their noise) and its standard error.
    alternatives : tuple of Alternative
        The other structures considered, best first.
    uncertain : tuple of Alternative
        Structures with other hidden states (other carriers, another number of hidden
        states) that explain the data equally well and are no larger than the reported
        one, or that the held-out data favour over it (paired held-out errors), or
        stage one's own law where it is larger, not the reported one with terms added,
        scores no worse and the held-out data lean towards it: the data cannot tell
        them apart; the simplest is reported.
    doubts : tuple of str
        Checks the reported system failed, each a sentence saying what it means: it
        could not be scored or does not reproduce held-out data down to their noise, its
        refinement did not converge, a hidden-equation coefficient is within two
        standard errors of zero, a term can be exchanged for another with almost no
        loss of fit, a term is supported only weakly, a term left out is nearly called
        for, or the system integrated over a whole recording blows up. Without
        refinement (``refine=False``) nothing was checked, and that is the doubt.
        Empty when every check passed.
    notes : tuple of str
        Remarks that are not doubts (a hidden state with no dynamics of its own, names
        that could not be used).
    refinement : Refinement or None
    coefficients : CoefficientSeries
        Stage one's result (first trajectory).
    all_times, all_observed, all_hidden : list of ndarray
        Every segment used, in the order of ``data_use.sources``.
    data_use : DataUse or None
        Recordings, segments and samples used, rows with missing values dropped, and
        where each segment came from (None in files written before version 4).
    timings : dict {stage: seconds}
        Wall time of the discovery by stage (differentiation, stage one's exact model,
        generator and posterior samples, smoothing, proposals, closure, refinement,
        term selection, held-out score, restatements, checks and result, other), each
        exclusive of the others; empty for results loaded from files.
    """

    times: np.ndarray
    observed: np.ndarray
    hidden: np.ndarray
    hidden_std: np.ndarray
    observed_names: tuple
    hidden_names: tuple
    hidden_states: tuple
    terms: tuple
    coefficients: CoefficientSeries
    score: float = math.nan
    score_se: float = math.nan
    alternatives: tuple = ()
    uncertain: tuple = ()
    refinement: Refinement | None = None
    notes: tuple = ()
    all_times: list = field(repr=False, default_factory=list)
    all_observed: list = field(repr=False, default_factory=list)
    all_hidden: list = field(repr=False, default_factory=list)
    hidden_initial: list = field(repr=False, default_factory=list)
    initial_state: np.ndarray | None = field(repr=False, default=None)
    doubts: tuple = ()
    data_use: DataUse | None = None
    timings: dict = field(repr=False, default_factory=dict)

    def __post_init__(self):
        object.__setattr__(self, "doubts", as_doubts(self.doubts))

    # ----------------------------------------------------------- views
    @property
    def confident(self) -> bool:
        """True when the reported system was checked by integration, no other
        structure explains the data as well (``uncertain`` is empty) and it passed every
        check (``doubts`` is empty). Read it before trusting an equation."""
        return (self.refinement is not None and bool(np.isfinite(self.score))
                and not self.uncertain and not self.doubts)

    @property
    def state_names(self) -> tuple[str, ...]:
        return self.observed_names + self.hidden_names

    @property
    def symbols(self) -> list[sp.Symbol]:
        return [sp.Symbol(n, real=True) for n in self.state_names]

    @property
    def hidden_terms(self) -> tuple:
        """Per hidden state, the (equation, feature) terms it enters (empty for a rate)."""
        return tuple(h.terms for h in self.hidden_states)

    @property
    def rhs(self) -> dict:
        """Time derivative of each state (sympy), built from :attr:`terms`."""
        out = {n: sp.Integer(0) for n in self.state_names}
        for term in self.terms:
            if term.value != 0:
                out[term.state] += sp.Float(term.value) * term.feature
        return out

    @property
    def equations(self) -> list[sp.Eq]:
        """``d state/dt = rhs`` as sympy equations, for display."""
        tt = sp.Symbol("t")
        rhs = self.rhs
        return [sp.Eq(sp.Derivative(sp.Function(n)(tt), tt), rhs[n]) for n in self.state_names]

    @property
    def states(self) -> np.ndarray:
        """Observed and hidden states side by side (first trajectory)."""
        return np.hstack([self.observed, self.hidden])

    def equation(self, state: str) -> dict:
        """The terms of ``d state/dt`` as {feature (sympy expression): coefficient}."""
        self._check_state(state)
        return {t.feature: t.value for t in self.terms if t.state == state and t.value != 0}

    def coefficient(self, state: str, feature) -> float:
        """Coefficient of ``feature`` (sympy expression or string such as ``"h*x"``) in
        ``d state/dt``; 0 if absent."""
        self._check_state(state)
        expr = sp.sympify(feature, locals={n: s for n, s in zip(self.state_names, self.symbols,
                                                                 strict=True)}) \
            if isinstance(feature, str) else sp.sympify(feature)
        unknown = {str(s) for s in expr.free_symbols} - set(self.state_names)
        if unknown:
            raise ValueError(f"feature {feature!r} uses {sorted(unknown)}, which are not states "
                             f"of this system; states are {list(self.state_names)}.")
        for term in self.terms:
            if term.state == state and sp.expand(term.feature - expr) == 0:
                return term.value
        return 0.0

    def _check_state(self, state):
        if state not in self.state_names:
            raise ValueError(f"Unknown state {state!r}; states are {list(self.state_names)}.")

    def vector_field(self) -> VectorField:
        """The closed vector field ``f(t, y)`` for numpy arrays or torch tensors."""
        rhs = self.rhs
        return VectorField(self.symbols, [rhs[n] for n in self.state_names])

    # ----------------------------------------------------------- checks
    def simulate(self, t=None, x0=None, *, max_steps=20_000) -> Simulation:
        """Integrate the closed system with torchdiffeq (dopri5, finite step budget).

        ``x0`` defaults to the fitted state at the first sample (observed and hidden);
        a blow-up or an exhausted budget is reported in the result's ``status``.
        """
        t = self.times if t is None else np.asarray(t, dtype=float)
        x0 = self.initial_state if x0 is None else np.asarray(x0, dtype=float)
        if x0.shape != (len(self.state_names),):
            raise ValueError(f"x0 must have shape ({len(self.state_names)},) for states "
                             f"{list(self.state_names)}; got shape {x0.shape}.")
        bound = 1e3 * max(1.0, float(np.nanmax(np.abs(self.states))))
        return integrate(self.vector_field(), t, x0, self.state_names, bound=bound,
                         max_steps=max_steps)

    def compare_hidden(self, true_hidden, *, with_observed=False) -> HiddenComparison:
        """R^2 of known hidden variables against the inferred ones after the best affine
        map (first trajectory).

        A hidden state is defined by the coefficient it carries, so it can be the true
        variable shifted by observed states (Rossler with z hidden: ``xdot = h`` with
        ``h = -y - z``), and by the observed terms its equation shows beside it: a state
        that is the coefficient of ``f`` in ``ds/dt`` is the true coefficient less
        ``g / f`` for every observed-only term ``g`` of ``ds/dt`` that ``f`` divides
        (Van der Pol seen through x: ``xdot = h + mu x - mu x^3 / 3`` with ``h = y -
        mu (x - x^3 / 3)``). ``with_observed=True`` lets the map use the observed states
        and those terms (``true ~ hidden @ scale + features @ observed_scale + offset``,
        the features named in ``observed_terms``).
        """
        truth = np.asarray(true_hidden, dtype=float)
        truth = truth[:, None] if truth.ndim == 1 else truth
        if truth.shape[0] != self.hidden.shape[0]:
            raise ValueError(f"true_hidden has {truth.shape[0]} rows but the hidden states have "
                             f"{self.hidden.shape[0]}; pass the series on the same times.")
        if not isinstance(with_observed, bool):
            raise TypeError(f"with_observed must be True or False; got {with_observed!r}.")
        terms = self._absorbed_observed_terms() if with_observed else ()
        symbols = self.symbols[:len(self.observed_names)]
        extra = [np.broadcast_to(sp.lambdify(symbols, term, "numpy")(*self.observed.T),
                                 (len(truth),)) for term in terms]
        design = np.column_stack([self.hidden, *extra, np.ones(len(truth))])
        coef, *_ = np.linalg.lstsq(design, truth, rcond=None)
        resid = truth - design @ coef
        r2 = 1 - np.sum(resid**2, axis=0) / np.sum((truth - truth.mean(axis=0)) ** 2, axis=0)
        n_h = self.hidden.shape[1]
        return HiddenComparison(r2, coef[:n_h], coef[-1],
                                coef[n_h:-1] if with_observed else None, terms)

    def _absorbed_observed_terms(self) -> tuple:
        """The observed states, then ``g / f`` for each observed-only term ``g`` beside a
        hidden state's carrier term ``f h`` in its equation, where ``f`` divides ``g``
        (built from the terms, see :meth:`compare_hidden`)."""
        observed = self.symbols[:len(self.observed_names)]
        out = list(observed)
        for hidden in self.hidden_states:
            if hidden.rate_of is not None or not hidden.terms:
                continue
            state = hidden.terms[0][0]
            h = sp.Symbol(hidden.name, real=True)
            # the carrier from the defining term (carrier * h, value 1), not from its name
            carrier = next((sp.cancel(t.feature / h) for t in self.terms
                            if t.state == state and t.fixed and t.feature.has(h)), None)
            if carrier is None or not carrier.free_symbols <= set(observed) | {sp.S.One}:
                continue
            for term in self.terms:
                if (term.state != state or term.fixed or term.value == 0
                        or not term.feature.free_symbols <= set(observed)):
                    continue
                quotient, remainder = sp.div(term.feature, carrier, *observed)
                if remainder == 0 and quotient.free_symbols and quotient not in out:
                    out.append(quotient)
        return tuple(out)

    def to_latex(self) -> str:
        """The equations as a LaTeX ``aligned`` block."""
        rhs = self.rhs
        lines = [rf"\dot{{{sp.latex(s)}}} &= {sp.latex(rhs[n])}"
                 for s, n in zip(self.symbols, self.state_names, strict=True)]
        return "\\begin{aligned}\n" + " \\\\\n".join(lines) + "\n\\end{aligned}"

    def summary(self) -> str:
        """The closed system, its coefficients with standard errors, how it was fitted
        and judged, doubts, equally good alternatives (or the runner-up) and notes
        (also ``str(result)``)."""
        return summary_text(self)

    def __str__(self) -> str:
        return self.summary()

    def __repr__(self) -> str:
        verdict = "confident" if self.confident else "not confident"
        score = f", score {self.score:.3g}" if np.isfinite(self.score) else ""
        extra = []
        if self.doubts:
            extra.append(f"{len(self.doubts)} doubt" + ("s" if len(self.doubts) > 1 else ""))
        if self.uncertain:
            extra.append(f"{len(self.uncertain)} equally good")
        more = "; " + ", ".join(extra) if extra else ""
        return (f"HiddenDiscovery({len(self.observed_names)} observed + "
                f"{len(self.hidden_names)} hidden: {', '.join(self.state_names)}; "
                f"{verdict}{score}{more})")

    def plot(self, truth=None, *, path=None, simulation=None, figsize=None):
        """Observed data against the closed system; hidden states with their band.

        Needs matplotlib (``pip install "latentsindy[plot]"``).

        Parameters
        ----------
        truth : array (n_times,) or (n_times, n_true), optional
            Known hidden variables (first trajectory), drawn after the best affine map
            into each hidden state's units.
        path : str or Path, optional
            Also save the figure there.
        simulation : Simulation, optional
            Reuse a ``simulate()`` result instead of integrating again.

        Returns
        -------
        matplotlib.figure.Figure
        """
        return plot_discovery(self, truth, simulation=simulation, figsize=figsize, path=path)

    # ----------------------------------------------------------- persistence
    def save(self, path) -> None:
        """Write the result to a ``.npz`` file (see :func:`load`)."""
        saving.save(self, path)
