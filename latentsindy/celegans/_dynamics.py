"""The switching cubic's fixed points and its integration under a switching input."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .._core.simulate import integrate
from ._switch import Switch

ORDER = ("x^3", "x^2", "x", "y")


@dataclass(frozen=True)
class FixedPoint:
    """A fixed point (x*, 0) of ``xdot = y, ydot = f(x) + d y + u`` for one u level.

    Attributes
    ----------
    x : float
    eigenvalues : tuple of complex
        Of the Jacobian ``[[0, 1], [f'(x*), d]]``.
    kind : str
        "stable focus", "stable node", "saddle", "unstable focus" or "unstable node".
    """

    x: float
    eigenvalues: tuple
    kind: str

    @property
    def stable(self) -> bool:
        return self.kind.startswith("stable")


def fixed_points(cubic: dict, level: float) -> tuple[FixedPoint, ...]:
    """Real fixed points for one input level, sorted by x.

    Examples
    --------
    >>> from latentsindy.celegans import PAPER_CUBIC
    >>> [round(p.x, 2) for p in fixed_points(PAPER_CUBIC, -0.266)]
    [-5.25]
    >>> [p.kind for p in fixed_points(PAPER_CUBIC, 0.044)]
    ['stable focus', 'saddle', 'stable focus']
    """
    a, b, c, d = (float(cubic[k]) for k in ORDER)
    roots = np.roots([a, b, c, level]) if a != 0 else np.roots([b, c, level])
    scale = max(1.0, float(np.max(np.abs(roots)))) if roots.size else 1.0
    real = np.sort(roots[np.abs(roots.imag) <= 1e-7 * scale].real)
    out = []
    for r in real:
        slope = 3 * a * r**2 + 2 * b * r + c
        disc = complex(d * d + 4 * slope)
        eig = ((d + np.sqrt(disc)) / 2, (d - np.sqrt(disc)) / 2)
        if slope > 0:
            kind = "saddle"
        else:
            stability = "stable" if d < 0 else "unstable"
            kind = f"{stability} {'focus' if disc.real < 0 else 'node'}"
        out.append(FixedPoint(float(r), tuple(complex(e) for e in eig), kind))
    return tuple(out)


def simulate(cubic: dict, switch: Switch, t, x, y):
    """x(t) of the model under the switch, from the data's state at the first frame.

    Each piece between switches has a constant input and is integrated with
    torchdiffeq's dopri5 under a finite step budget, so the jumps of u are resolved
    exactly; a blow-up leaves NaN behind it.
    """
    t = np.asarray(t, dtype=float)
    a, b, c, d = (float(cubic[k]) for k in ORDER)
    bound = 100.0 * (float(np.max(np.abs(x))) + float(np.max(np.abs(y))) + 1.0)
    edges = np.concatenate([[t[0]], switch.switch_times, [t[-1]]])
    out = np.full(t.size, np.nan)
    state = np.array([x[0], y[0]], dtype=float)
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        level = float(switch.at(0.5 * (lo + hi)))
        inside = (t > lo) & (t < hi)
        grid = np.unique(np.concatenate([[lo], t[inside], [hi]]))

        def field(_, s, level=level):
            return torch.stack([s[1], a * s[0] ** 3 + b * s[0] ** 2 + c * s[0] + d * s[1]
                                + level])

        sim = integrate(field, grid, state, ("x", "y"), bound=bound)
        mask = (t >= lo) & (t <= hi)
        out[mask] = sim.x[np.searchsorted(grid, t[mask]), 0]  # every t[mask] is in grid
        if not sim.success:
            break
        state = sim.x[-1]
    return out


def nrmse(simulated, data) -> float:
    """Root-mean-square error over the data's standard deviation (NaN counts as failure:
    inf)."""
    if not np.all(np.isfinite(simulated)):
        return float("inf")
    return float(np.sqrt(np.mean((simulated - data) ** 2)) / np.std(data))
