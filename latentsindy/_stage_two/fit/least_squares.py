"""The least-squares engine of refinement: Levenberg-Marquardt on the multiple-shooting
equations (:mod:`.shooting`), its stopping rules and give-up checks, and the free
coefficients' covariance."""

from __future__ import annotations

import numpy as np

from ..._core.budget import spent
from .normal_equations import solve
from .shooting import BlowUp

# A fit stops once the Gauss-Newton model's remaining decrease of the misfit (noise
# variances) is below this. That decrease is the squared distance to the model's
# minimum in standard errors, jointly over all coefficients and starts: the fit stops
# within 0.22 of them, while every decision made on the misfit (term prices ~10,
# ambiguity 4) is forty times coarser. Not for held-out folds (cross_validate), whose
# misfit does not contain the data that is scored.
RESOLUTION = 0.05
# A fit still this many times above the misfit it must reach to count (a hypothesis's
# first fit: the best so far; a refit of term selection or of a check: the misfit at
# which its move wins or its check turns) after half its iterations, or after a pass,
# gives up there: it cannot compete, and running on costs as much again.
HOPELESS = 50.0


def degrees_of_freedom(n_data, system, starts) -> int:
    """Data less the free coefficients and segment starts (at least 1)."""
    return max(n_data - system.n_free - starts.size, 1)


class GiveUpWatch:
    """The give-up checks of one fit (:meth:`Problem.fit`): the data misfits at which it
    went on, and the one at which it gave up (None if it never did).

    A fit's path is the same under any bound until a check stops it, so from these the
    fit under another bound can be told to be this same fit (:meth:`same_under`): the
    first fits of several proposals run side by side, each with the bound known at each
    of its checks, and are kept exactly when the one-by-one order would have given them
    the same fit.
    """

    def __init__(self):
        self.went_on = []
        self.gave_up_at = None
        self.dof = None

    def check(self, data_cost: float, limit: float) -> bool:
        """Whether a fit at ``data_cost`` gives up against ``limit`` (recorded)."""
        if data_cost > limit:
            self.gave_up_at = data_cost
            return True
        self.went_on.append(data_cost)
        return False

    def same_under(self, give_up: float) -> bool:
        """Whether the fit with ``give_up`` (per degree of freedom, as ``fit`` takes it)
        would have been this one: it goes on at every check this one went on at, and
        gives up where this one did."""
        limit = give_up * self.dof if self.dof is not None else np.inf
        return (all(c <= limit for c in self.went_on)
                and (self.gave_up_at is None or self.gave_up_at > limit))


def levenberg_marquardt(problem, system, values, starts, weights, rho, max_iterations,
                         tolerance=1e-6, resolution=RESOLUTION, give_up=lambda: np.inf,
                         watch=None):
    """Marquardt-scaled Levenberg-Marquardt; every trial point is integrated with its
    sensitivities, so an accepted step needs no second integration. Stops when a step
    lowers the cost by less than ``tolerance`` (relative), when the Gauss-Newton
    model's remaining decrease is below ``resolution`` (noise variances; no
    integration is spent on it), when no step lowers the cost, or when the data misfit
    is above ``give_up()`` after half the iterations (``watch`` records that check), or
    when the discovery's ``max_time`` is spent (:mod:`.._core.budget`)."""
    watch = GiveUpWatch() if watch is None else watch
    n_free = system.n_free
    eq = problem.equations(system.with_free(values), starts, weights, rho)
    mu, converged, iterations, accepted = 1e-3, False, 0, True
    while iterations < max_iterations:
        if spent("fits stopped before converging"):  # max_time: the fit so far
            break
        if accepted:  # a new point: its matrix serves every damped solve there
            a = eq.matrix()
            diag = a.diagonal()
            scale = np.maximum(diag, 1e-12 * max(diag.max(), 1e-300))
        # at a point just reached, the undamped Gauss-Newton model's whole remaining
        # decrease (g' A^-1 g) below the resolution ends the fit without integrating
        # another step (the damped step's decrease would understate it in a long valley
        # of correlated coefficients, and stop there far from the minimum)
        if accepted and resolution > 0:
            if -(eq.grad @ solve(a, -eq.grad, 1e-10 * scale)) < resolution:
                converged = True
                break
        if iterations >= max_iterations // 2 and watch.check(eq.data_cost, give_up()):
            break
        step = solve(a, -eq.grad, mu * scale)
        iterations += 1
        trial_values = values + step[:n_free]
        trial_starts = starts + step[n_free:].reshape(starts.shape)
        try:
            trial = problem.equations(system.with_free(trial_values), trial_starts, weights,
                                      rho)
            better = np.isfinite(trial.cost) and trial.cost < eq.cost
        except BlowUp:
            better = False
        if better:
            decrease = eq.cost - trial.cost
            values, starts, eq = trial_values, trial_starts, trial
            mu, accepted = max(mu / 3.0, 1e-9), True
            if decrease < tolerance * eq.cost:
                converged = True
                break
        else:
            mu, accepted = mu * 8.0, False
            if mu > 1e8:
                converged = True  # no step lowers the cost: a (local) minimum
                break
    return values, starts, eq, iterations, converged


def covariance(eq, n_free):
    """Covariance of the free coefficients: the coefficient block of (J^T J)^-1 times
    the residual variance per data point (1 when the noise level is right)."""
    if n_free == 0:
        return np.zeros((0, 0))
    a = eq.matrix()
    unit = np.zeros((a.shape[0], n_free))
    unit[np.arange(n_free), np.arange(n_free)] = 1.0
    try:
        block = solve(a, unit)[:n_free]
    except (np.linalg.LinAlgError, RuntimeError):
        return np.full((n_free, n_free), np.nan)
    return block
