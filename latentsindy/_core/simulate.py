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
        States; rows after a failure are NaN.
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
    and reported as a blow-up; ``max_steps`` caps the solver's steps over the whole
    run (counted as right-hand-side evaluations / 6, dopri5's cost per step).
    """
    t = np.array(t, dtype=float)  # a writable copy: torch refuses read-only buffers
    y0 = torch.tensor(np.asarray(x0, dtype=float))
    tt = torch.tensor(t)
    count = [0]

    def func(ti, y):
        count[0] += 1
        if count[0] > 6 * max_steps:
            raise _Budget()
        if not bool(torch.all(torch.isfinite(y))) or float(y.abs().max()) > bound:
            raise _BlowUp(float(ti))
        return field(ti, y)

    nan = np.full((len(t), len(x0)), np.nan)
    try:
        with torch.no_grad():
            sol = odeint(func, y0, tt, method="dopri5", rtol=rtol, atol=atol)
    except _BlowUp as err:
        return Simulation(t, nan, tuple(state_names), "blow_up",
                          f"The closed system blew up ({err}); the discovered equations are "
                          "unstable from this initial condition. Try another x0, a shorter "
                          "horizon, or refit with more data or less noise.", count[0])
    except _Budget:
        return Simulation(t, nan, tuple(state_names), "step_budget",
                          f"The solver used its budget of {max_steps} steps before reaching "
                          f"t={t[-1]:.6g} (the system is stiff or nearly singular); pass a larger "
                          "max_steps or a shorter horizon.", count[0])
    x = sol.numpy()
    return Simulation(t, x, tuple(state_names), "success", "Integrated to the final time.",
                      count[0])
