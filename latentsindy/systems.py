"""Synthetic systems with known truth: the paper's test beds and systems with a state to hide.

Coefficient shapes are small frozen callables of time; systems integrate the ODE
accurately and return a :class:`SystemData` with the states, exact derivatives and
the true coefficients. Autonomous systems whose states can be hidden
(:func:`lotka_volterra`, :func:`lorenz`, :func:`fitzhugh_nagumo`,
:func:`modulated_oscillator`) are test beds for :func:`latentsindy.discover_hidden`.

Examples
--------
>>> from latentsindy import systems
>>> data = systems.harmonic_oscillator(A=systems.Switch(-1.0, -4.0, at=5.0), n_times=500)
>>> data.x.shape, data.terms[("x", "y")].shape
((500, 2), (500,))
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

from ._core.shapes import Constant, FourierSeries, Sigmoid, Sinusoid, Switch, Switches

__all__ = [
    "Constant",
    "Switch",
    "Switches",
    "Sigmoid",
    "Sinusoid",
    "FourierSeries",
    "SystemData",
    "fitzhugh_nagumo",
    "harmonic_oscillator",
    "lorenz",
    "lotka_volterra",
    "modulated_oscillator",
]


Coefficient = float | Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class SystemData:
    """A simulated system.

    Attributes
    ----------
    t : ndarray, shape (n_times,)
    x : ndarray, shape (n_times, n_states)
        Observed states (with measurement noise, if any).
    x_clean : ndarray, shape (n_times, n_states)
        Noise-free states.
    x_dot : ndarray, shape (n_times, n_states)
        Exact time derivatives of ``x_clean``.
    state_names : tuple of str
    parameters : dict of str -> ndarray
        Each named coefficient over time (with coefficient noise, if any).
    terms : dict of (state, feature) -> ndarray
        The true equations: ``d state/dt = sum terms[(state, f)](t) * f``, with
        feature names in pysindy's spelling (``"x y"`` is the product x*y).
    """

    t: np.ndarray
    x: np.ndarray
    x_clean: np.ndarray
    x_dot: np.ndarray
    state_names: tuple[str, ...]
    parameters: dict[str, np.ndarray]
    terms: dict[tuple[str, str], np.ndarray]

    @property
    def dt(self) -> float:
        return float(self.t[1] - self.t[0])

    def true_coefficients(self, state_names, feature_names) -> np.ndarray:
        """Truth laid out as ``(n_times, n_states, n_features)`` for given names."""
        out = np.zeros((len(self.t), len(state_names), len(feature_names)))
        known = set(self.terms)
        for i, s in enumerate(state_names):
            for j, f in enumerate(feature_names):
                if (s, f) in self.terms:
                    out[:, i, j] = self.terms[(s, f)]
                    known.discard((s, f))
        if known:
            raise ValueError(
                f"The true equations use terms {sorted(known)} that are not among "
                f"feature_names={list(feature_names)}; use a library that contains them."
            )
        return out


def _as_function(value: Coefficient, name: str) -> Callable[[np.ndarray], np.ndarray]:
    if callable(value):
        return value
    if isinstance(value, int | float | np.floating | np.integer):
        return Constant(float(value))
    raise TypeError(f"{name} must be a number or a callable of t; got {type(value).__name__}.")


def _simulate(rhs, x0, t, parameters, coefficient_noise, rng):
    """Integrate ``rhs(t, x, params)`` with params sampled on the time grid."""
    series = {k: np.asarray(f(t), dtype=float) for k, f in parameters.items()}
    if coefficient_noise:
        series = {k: v + coefficient_noise * rng.standard_normal(v.shape)
                  for k, v in series.items()}

    def at(ti):
        if not coefficient_noise:  # the exact coefficient, not a piecewise-linear one
            return {k: float(f(ti)) for k, f in parameters.items()}
        return {k: np.interp(ti, t, v) for k, v in series.items()}

    max_step = (t[-1] - t[0]) / 200.0
    sol = solve_ivp(
        lambda ti, xi: rhs(xi, at(ti)), (t[0], t[-1]), np.asarray(x0, dtype=float),
        t_eval=t, method="DOP853", rtol=1e-10, atol=1e-10, max_step=max_step,
    )
    if not sol.success:
        raise RuntimeError(f"Simulation failed: {sol.message}")
    x = sol.y.T
    x_dot = np.stack([rhs(x[k], {n: v[k] for n, v in series.items()}) for k in range(len(t))])
    return x, x_dot, series


def _finish(t, x, x_dot, names, series, terms, noise, rng) -> SystemData:
    scale = x.std(axis=0)
    x_noisy = x + noise * scale * rng.standard_normal(x.shape) if noise else x.copy()
    return SystemData(t, x_noisy, x, x_dot, tuple(names), series, terms)


def _time_grid(t_end, n_times, t=None):
    """``n_times`` equally spaced times from 0 to ``t_end``, or the given sample times."""
    if t is not None:
        arr = np.array(t, dtype=float)
        if arr.ndim != 1 or len(arr) < 2 or not np.all(np.isfinite(arr)) \
                or np.any(np.diff(arr) <= 0):
            raise ValueError("t must be a 1-D array of at least 2 finite, strictly "
                             f"increasing sample times; got shape {arr.shape}.")
        return arr
    if n_times < 2:
        raise ValueError(f"n_times must be at least 2; got {n_times}.")
    return np.linspace(0.0, t_end, n_times)


def harmonic_oscillator(
    A: Coefficient = -1.0,
    B: Coefficient = 1.0,
    *,
    t_end: float = 10.0,
    n_times: int = 1000,
    t: Sequence[float] | None = None,
    x0: Sequence[float] = (1.0, 0.0),
    noise: float = 0.0,
    coefficient_noise: float = 0.0,
    seed: int = 0,
) -> SystemData:
    """Non-autonomous oscillator ``xdot = A(t) y``, ``ydot = B(t) x``.

    ``noise`` is measurement noise as a fraction of each state's standard deviation;
    ``coefficient_noise`` is an absolute standard deviation added to A and B. Every
    system samples ``n_times`` equally spaced times from 0 to ``t_end``, or the sample
    times ``t`` when given (irregular sampling; the integration starts at ``t[0]``).
    """
    rng = np.random.default_rng(seed)
    t = _time_grid(t_end, n_times, t)
    params = {"A": _as_function(A, "A"), "B": _as_function(B, "B")}

    def rhs(s, p):
        return np.array([p["A"] * s[1], p["B"] * s[0]])

    x, x_dot, series = _simulate(rhs, x0, t, params, coefficient_noise, rng)
    terms = {("x", "y"): series["A"], ("y", "x"): series["B"]}
    return _finish(t, x, x_dot, ("x", "y"), series, terms, noise, rng)


def lorenz(
    sigma: Coefficient = 10.0,
    rho: Coefficient = 28.0,
    beta: Coefficient = 8.0 / 3.0,
    *,
    t_end: float = 20.0,
    n_times: int = 2000,
    t: Sequence[float] | None = None,
    x0: Sequence[float] = (-8.0, 7.0, 27.0),
    noise: float = 0.0,
    coefficient_noise: float = 0.0,
    seed: int = 0,
) -> SystemData:
    """Lorenz system with any of sigma, rho, beta varying in time."""
    rng = np.random.default_rng(seed)
    t = _time_grid(t_end, n_times, t)
    params = {
        "sigma": _as_function(sigma, "sigma"),
        "rho": _as_function(rho, "rho"),
        "beta": _as_function(beta, "beta"),
    }

    def rhs(s, p):
        x, y, z = s
        return np.array([p["sigma"] * (y - x), x * (p["rho"] - z) - y, x * y - p["beta"] * z])

    x, x_dot, series = _simulate(rhs, x0, t, params, coefficient_noise, rng)
    one = np.ones_like(t)
    terms = {
        ("x", "x"): -series["sigma"],
        ("x", "y"): series["sigma"],
        ("y", "x"): series["rho"],
        ("y", "y"): -one,
        ("y", "x z"): -one,
        ("z", "x y"): one,
        ("z", "z"): -series["beta"],
    }
    return _finish(t, x, x_dot, ("x", "y", "z"), series, terms, noise, rng)


def lotka_volterra(
    alpha: Coefficient = 1.0,
    beta: Coefficient = 0.1,
    gamma: Coefficient = 1.5,
    delta: Coefficient = 0.075,
    *,
    t_end: float = 20.0,
    n_times: int = 2000,
    t: Sequence[float] | None = None,
    x0: Sequence[float] = (10.0, 5.0),
    noise: float = 0.0,
    coefficient_noise: float = 0.0,
    seed: int = 0,
) -> SystemData:
    """Predator-prey ``xdot = alpha x - beta x y``, ``ydot = -gamma y + delta x y``."""
    rng = np.random.default_rng(seed)
    t = _time_grid(t_end, n_times, t)
    params = {
        "alpha": _as_function(alpha, "alpha"),
        "beta": _as_function(beta, "beta"),
        "gamma": _as_function(gamma, "gamma"),
        "delta": _as_function(delta, "delta"),
    }

    def rhs(s, p):
        x, y = s
        return np.array([p["alpha"] * x - p["beta"] * x * y, -p["gamma"] * y + p["delta"] * x * y])

    x, x_dot, series = _simulate(rhs, x0, t, params, coefficient_noise, rng)
    terms = {
        ("x", "x"): series["alpha"],
        ("x", "x y"): -series["beta"],
        ("y", "y"): -series["gamma"],
        ("y", "x y"): series["delta"],
    }
    return _finish(t, x, x_dot, ("x", "y"), series, terms, noise, rng)


def fitzhugh_nagumo(
    a: float = 0.7,
    b: float = 0.8,
    epsilon: float = 0.08,
    current: float = 0.5,
    *,
    t_end: float = 150.0,
    n_times: int = 2000,
    t: Sequence[float] | None = None,
    x0: Sequence[float] = (-1.0, 1.0),
    noise: float = 0.0,
    seed: int = 0,
) -> SystemData:
    """FitzHugh-Nagumo neuron: ``vdot = v - v^3/3 - w + current``,
    ``wdot = epsilon (v + a - b w)``.

    A cubic oscillator driven by the recovery variable w, which follows its own ODE
    coupled to v: with only v observed, ``current - w`` is a hidden additive input.
    """
    rng = np.random.default_rng(seed)
    t = _time_grid(t_end, n_times, t)

    def rhs(s, p):
        v, w = s
        return np.array([v - v**3 / 3.0 - w + current, epsilon * (v + a - b * w)])

    x, x_dot, _ = _simulate(rhs, x0, t, {}, 0.0, rng)
    one = np.ones_like(t)
    terms = {("v", "1"): current * one, ("v", "v"): one, ("v", "v^3"): -one / 3.0,
             ("v", "w"): -one, ("w", "1"): epsilon * a * one, ("w", "v"): epsilon * one,
             ("w", "w"): -epsilon * b * one}
    return _finish(t, x, x_dot, ("v", "w"), {}, terms, noise, rng)


def modulated_oscillator(
    omega: float = 1.5,
    a: float = 0.0,
    b: float = 0.0,
    k: float = 1.0,
    epsilon: float = 1.0,
    *,
    t_end: float = 40.0,
    n_times: int = 2000,
    t: Sequence[float] | None = None,
    x0: Sequence[float] = (1.0, 0.0, 0.6),
    noise: float = 0.0,
    seed: int = 0,
) -> SystemData:
    """An oscillator whose growth rate z is driven by its own amplitude:
    ``xdot = (a + z) x - omega y``, ``ydot = omega x + (b + k z) y``,
    ``zdot = epsilon (1 - x^2 - y^2)``.

    With x and y observed, the hidden z enters both equations (two coefficients that
    are affine images of one another); the amplitude swells and fades periodically.
    """
    rng = np.random.default_rng(seed)
    t = _time_grid(t_end, n_times, t)

    def rhs(s, p):
        x, y, z = s
        return np.array([(a + z) * x - omega * y, omega * x + (b + k * z) * y,
                         epsilon * (1.0 - x * x - y * y)])

    x, x_dot, _ = _simulate(rhs, x0, t, {}, 0.0, rng)
    one = np.ones_like(t)
    terms = {("x", "x"): a * one, ("x", "x z"): one, ("x", "y"): -omega * one,
             ("y", "x"): omega * one, ("y", "y"): b * one, ("y", "y z"): k * one,
             ("z", "1"): epsilon * one, ("z", "x^2"): -epsilon * one,
             ("z", "y^2"): -epsilon * one}
    return _finish(t, x, x_dot, ("x", "y", "z"), {}, terms, noise, rng)
