"""Integration of closed systems with torchdiffeq: a finite budget, blow-ups reported."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torchdiffeq import odeint


class _Budget(Exception):
    pass


class _BlowUp(Exception):
    def __init__(self, t):
        super().__init__(f"state left the bounded region at t={t:.6g}")
        self.t = t


@dataclass(frozen=True)
class Simulation:
    """Result of integrating a closed system.

    Attributes
    ----------
    t : ndarray, shape (n_times,)
    x : ndarray, shape (n_times, n_states)
        States; on a failure, the rows after where the solver got are NaN.
    state_names : tuple of str
    status : {"success", "blow_up", "step_budget"}
    message : str
        What happened and, on failure, what to try.
    n_evaluations : int
        Right-hand-side evaluations used.
    """

    t: np.ndarray
    x: np.ndarray
    state_names: tuple[str, ...]
    status: str
    message: str
    n_evaluations: int

    @property
    def success(self) -> bool:
        return self.status == "success"


def integrate(field, t, x0, state_names, *, bound, max_steps=20_000, rtol=1e-8, atol=1e-10):
    """Integrate ``field`` from ``x0`` over ``t`` (dopri5, float64).

    ``bound`` is the largest magnitude any state may reach before the run is stopped
    and reported as a blow-up; ``max_steps`` caps the solver's steps over the run
    (counted as right-hand-side evaluations / 6, dopri5's cost per step). On a failure
    the rows up to where the solver got are integrated again, in pieces of ``t`` (the
    solver keeps no rows of a run it stops), with as many evaluations as the failed
    run used plus ``RESTART`` for each piece; the rows after them are NaN.
    """
    t = np.array(t, dtype=float)  # a writable copy: torch refuses read-only buffers
    y0 = torch.tensor(np.asarray(x0, dtype=float))
    count, limit, reached = [0], [6 * max_steps], [float(t[0])]

    def func(ti, y):
        count[0] += 1
        if count[0] > limit[0]:
            raise _Budget()
        if not bool(torch.all(torch.isfinite(y))) or float(y.abs().max()) > bound:
            raise _BlowUp(float(ti))
        reached[0] = max(reached[0], float(ti))
        return field(ti, y)

    try:
        with torch.no_grad():
            sol = odeint(func, y0, torch.tensor(t), method="dopri5", rtol=rtol, atol=atol)
    except _BlowUp as err:
        status = "blow_up"
        message = (f"The closed system blew up ({err}); the discovered equations are "
                   "unstable from this initial condition. Try another x0, a shorter "
                   "horizon, or refit with more data or less noise.")
    except _Budget:
        status = "step_budget"
        message = (f"The solver used its budget of {max_steps} steps before reaching "
                   f"t={t[-1]:.6g} (the system is stiff or nearly singular); pass a larger "
                   "max_steps or a shorter horizon.")
    else:
        return Simulation(t, sol.numpy(), tuple(state_names), "success",
                          "Integrated to the final time.", count[0])
    used = count[0]
    count[0], limit[0] = 0, used  # the rerun: what the failed run used, RESTART a piece
    x = _before(func, y0, t, reached[0], rtol, atol, limit)
    return Simulation(t, x, tuple(state_names), status, message, used + count[0])


RESTART = 60  # evaluations allowed for each restart of the rerun (a step size found again)


def _before(func, y0, t, until, rtol, atol, limit, chunk=64):
    """The states at the times of ``t`` up to ``until`` (where the whole run failed),
    integrated ``chunk`` intervals at a time and, from a chunk that fails, one interval
    at a time, so that each row is kept once reached; NaN after them and wherever this
    run fails too. Each piece raises ``limit`` by ``RESTART``."""
    x = np.full((len(t), len(y0)), np.nan)
    x[0] = y0.numpy()
    last = int(np.searchsorted(t, until, side="right")) - 1  # the last row to reach
    i, y = 0, y0
    with torch.no_grad():
        while i < last:
            j = min(i + chunk, last)
            limit[0] += RESTART
            try:
                sol = odeint(func, y, torch.tensor(t[i:j + 1]), method="dopri5",
                             rtol=rtol, atol=atol)
            except (_BlowUp, _Budget):
                if chunk == 1:
                    break
                chunk = 1
                continue
            x[i + 1:j + 1] = sol[1:].numpy()
            i, y = j, sol[-1]
    return x
