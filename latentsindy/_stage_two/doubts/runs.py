"""The whole-recording run: the closed system integrated over each recording from its
fitted initial state, with a finite budget; a blow-up or a run out of budget is a doubt."""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from ..._core.doubt import Doubt

FREE_RUN_RTOL = 1e-4  # a blow-up check, not a fit: a loose tolerance suffices


FREE_RUN_BUDGET = 60_000  # right-hand-side evaluations per recording


def free_run_doubt(result, trajectories):
    """A doubt when the closed system, integrated over a whole recording from its fitted
    initial state, blows up or exhausts its step budget.

    The refinement fits and the judge scores the system segment by segment (multiple
    shooting), so a wrong law that follows the data over short stretches can fit and
    score as well as the truth; over the whole recording it need not stay near the
    data at all. A law that reproduces a recording keeps a bounded trajectory over it
    (chaos may take it elsewhere on the attractor, not to infinity), so a blow-up
    (any state beyond 1000 times the largest fitted magnitude) is a failed check (a
    non-spiking Rossler with z hidden at 1% noise: a six-term hidden law fitted the
    segments to their noise, confidently, and blew up within the recording). LSODA
    (stiffness detected, so a stiff law is not mistaken for an unstable one), about
    0.1-0.2 s per recording of 2000 samples.
    """
    field = result.vector_field()
    for k, (t, states) in enumerate(zip(result.all_times, trajectories, strict=True)):
        status = bounded_run(field, t, states)
        if status == "success":
            continue
        where = f"recording segment {k}" if len(trajectories) > 1 else "the recording"
        what = {"blow_up": "blows up",
                "step_budget": "exhausts its step budget (stiff or nearly singular)"}.get(
                    status, "could not be integrated (the solver failed)")
        return (Doubt("free run",
                f"integrated over {where} from its fitted initial state (not segment by "
                f"segment, as it was fitted and scored), the closed system {what}: it "
                "follows the data over short stretches only, which a wrong law can do; more "
                "data, less noise or another closure_library may settle it"),)
    return ()


class _Budget(Exception):
    pass


def bounded_run(field, t, states):
    """"success", "blow_up" (a state beyond 1000 times the fitted states' largest
    magnitude, or not finite), "step_budget" or "failed" for a run over ``t`` from
    ``states[0]``."""
    scale = max(1.0, float(np.nanmax(np.abs(states))))
    count = [0]

    def rhs(ti, y):
        count[0] += 1
        if count[0] > FREE_RUN_BUDGET:
            raise _Budget
        return np.asarray(field(ti, y), dtype=float)

    def escaped(ti, y):
        return 1e3 * scale - float(np.max(np.abs(y)))

    escaped.terminal = True
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            sol = solve_ivp(rhs, (float(t[0]), float(t[-1])), np.asarray(states[0], float),
                            method="LSODA", rtol=FREE_RUN_RTOL,
                            atol=FREE_RUN_RTOL * 1e-3 * scale, events=escaped)
    except _Budget:
        return "step_budget"
    if sol.status == 1 or not np.all(np.isfinite(sol.y)):
        return "blow_up"
    return "success" if sol.success else "failed"
