"""Randomised families of systems with a hidden state, and their truth in sympy.

Each family draws parameters and initial conditions from seeded ranges, simulates the
system with ``latentsindy.systems`` and states the truth as a closed sympy system in the
observed states and the *true* hidden variables, with symbolic parameters (so a term
that is structurally absent is an exact zero, whatever the draw). The evaluation
(``_scoring.py``) moves that truth into the variables latentsindy reports.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pysindy as ps
import sympy as sp
from scipy.integrate import solve_ivp

from latentsindy import systems


@dataclass(frozen=True)
class Draw:
    """One simulated case: observed data, the truth and the hidden series."""

    family: str
    params: dict[str, float]
    t: np.ndarray
    observed: np.ndarray  # (T, n_observed), noisy
    observed_clean: np.ndarray
    observed_names: tuple[str, ...]
    hidden_true: np.ndarray  # (T, n_true_hidden), noise-free
    truth: dict[str, Any]  # "rhs": {name: expr}, "hidden": [symbols], "values": {sym: float}
    natural: tuple  # the hidden states in latentsindy's terms (see _scoring.definitions)
    # score the hidden states by R^2 of each true variable from the hidden *and* observed
    # states (affine): with several hidden states defined through one another, each is
    # the true variable up to observed terms (Lorenz from x: h1 = sigma (rho - z))
    with_observed: bool = False


@dataclass(frozen=True)
class Family:
    name: str
    description: str
    library: Any  # a callable returning a fresh pysindy library
    draw: Any  # (rng, noise, seed, sampling) -> Draw


def _sym(names):
    return [sp.Symbol(n, real=True) for n in names]


def _times(sampling, t_end):
    """Sample times from ``sampling(t_end)``, or None (2000 equally spaced samples)."""
    return None if sampling is None else np.asarray(sampling(t_end), dtype=float)


# --------------------------------------------------------------------- Lotka-Volterra
def _lotka_volterra(rng, noise, seed, sampling=None):
    p = {"alpha": rng.uniform(0.6, 1.4), "beta": rng.uniform(0.05, 0.2),
         "gamma": rng.uniform(0.6, 1.6), "delta": rng.uniform(0.02, 0.1)}
    x_eq, y_eq = p["gamma"] / p["delta"], p["alpha"] / p["beta"]
    x0 = (x_eq * rng.uniform(0.25, 0.75), y_eq * rng.uniform(0.6, 1.4))
    t_end = 5 * 2 * np.pi / np.sqrt(p["alpha"] * p["gamma"])
    d = systems.lotka_volterra(p["alpha"], p["beta"], p["gamma"], p["delta"], t_end=t_end,
                               n_times=2000, x0=x0, noise=noise, seed=seed,
                               t=_times(sampling, t_end))
    x, y = _sym("xy")
    a, b, g, dl = sp.symbols("alpha beta gamma delta", positive=True)
    rhs = {x: a * x - b * x * y, y: -g * y + dl * x * y}
    values = {a: p["alpha"], b: p["beta"], g: p["gamma"], dl: p["delta"]}
    return Draw("lotka_volterra", p, d.t, d.x[:, :1], d.x_clean[:, :1], ("x",),
                d.x_clean[:, 1:], {"rhs": rhs, "hidden": [y], "values": values},
                (("x", "x"),))


# ------------------------------------------------------- oscillators with a hidden B(t)
def _oscillator(sigmoid):
    def draw(rng, noise, seed, sampling=None):
        A = -rng.uniform(2.0, 5.0)
        phase = rng.uniform(0, 2 * np.pi)
        x0 = (np.cos(phase), np.sin(phase))
        x, y = _sym("xy")
        sA = sp.Symbol("A")
        if sigmoid:
            t_end = 10.0
            lo = rng.uniform(1.5, 2.5)
            hi = lo + rng.choice([-1, 1]) * rng.uniform(0.5, 1.2)
            rate, at = rng.uniform(0.8, 2.0), rng.uniform(0.35, 0.65) * t_end
            B = systems.Sigmoid(lo, hi, at=at, sharpness=rate)
            p = {"A": A, "low": lo, "high": hi, "rate": rate, "at": at}
            b = sp.Symbol("B", real=True)
            sl, sh, sr = sp.symbols("low high rate")
            rhs = {x: sA * y, y: b * x, b: sr * (b - sl) * (sh - b) / (sh - sl)}
            hidden = [b]
            values = {sA: A, sl: lo, sh: hi, sr: rate}
            natural = (("y", "x"),)
        else:
            t_end = 30.0
            b0, amp = rng.uniform(2.0, 3.0), rng.uniform(0.3, 0.8)
            omega, ph = rng.uniform(0.4, 0.8), rng.uniform(0, 2 * np.pi)
            B = systems.Sinusoid(b0, amp, omega / (2 * np.pi), ph)
            p = {"A": A, "offset": b0, "amplitude": amp, "omega": omega, "phase": ph}
            b, c = sp.Symbol("B", real=True), sp.Symbol("C", real=True)
            sb0, som = sp.symbols("b0 omega")
            rhs = {x: sA * y, y: b * x, b: c, c: -som**2 * (b - sb0)}
            hidden = [b, c]
            values = {sA: A, sb0: b0, som: omega}
            natural = (("y", "x"), "rate")
        d = systems.harmonic_oscillator(A=A, B=B, t_end=t_end, n_times=2000, x0=x0,
                                        noise=noise, seed=seed, t=_times(sampling, t_end))
        series = d.parameters["B"][:, None]
        if not sigmoid:  # B and its rate
            series = np.column_stack([series[:, 0], amp * omega * np.cos(omega * d.t + ph)])
        return Draw("oscillator_" + ("logistic" if sigmoid else "sinusoid"), p, d.t, d.x,
                    d.x_clean, ("x", "y"), series, {"rhs": rhs, "hidden": hidden,
                                                   "values": values}, natural)
    return draw


# --------------------------------------------------------------- FitzHugh-Nagumo
def _fitzhugh_nagumo(rng, noise, seed, sampling=None):
    for _ in range(100):  # keep draws that oscillate (the rest sit at a fixed point)
        p = {"a": rng.uniform(0.7, 0.9), "b": rng.uniform(0.6, 0.8),
             "epsilon": rng.uniform(0.06, 0.12), "current": rng.uniform(0.2, 0.5)}
        x0 = (rng.uniform(-2.0, 2.0), rng.uniform(-0.5, 1.5))
        d = systems.fitzhugh_nagumo(p["a"], p["b"], p["epsilon"], p["current"],
                                    t_end=12.0 / p["epsilon"], n_times=2000, x0=x0,
                                    noise=noise, seed=seed,
                                    t=_times(sampling, 12.0 / p["epsilon"]))
        tail = d.x_clean[len(d.t) // 2:, 0]
        if tail.max() - tail.min() > 2.0:
            break
    v, w = _sym("vw")
    a, b, e, c = sp.symbols("a b epsilon I")
    rhs = {v: v - v**3 / 3 - w + c, w: e * (v + a - b * w)}
    values = {a: p["a"], b: p["b"], e: p["epsilon"], c: p["current"]}
    return Draw("fitzhugh_nagumo", p, d.t, d.x[:, :1], d.x_clean[:, :1], ("v",),
                d.x_clean[:, 1:], {"rhs": rhs, "hidden": [w], "values": values},
                (("v", "1"),))


# ------------------------------------------------------------- Lorenz, z hidden
def _lorenz(rng, noise, seed, sampling):
    """A Lorenz draw on the attractor (after a burn-in), its truth and values."""
    p = {"sigma": rng.uniform(8.0, 12.0), "rho": rng.uniform(24.0, 32.0),
         "beta": rng.uniform(2.0, 3.2)}
    start = (rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(15, 35))
    burn = systems.lorenz(p["sigma"], p["rho"], p["beta"], t_end=10.0, n_times=1001,
                          x0=start)
    d = systems.lorenz(p["sigma"], p["rho"], p["beta"], t_end=20.0, n_times=2000,
                       x0=burn.x_clean[-1], noise=noise, seed=seed, t=_times(sampling, 20.0))
    x, y, z = _sym("xyz")
    s, r, b = sp.symbols("sigma rho beta")
    rhs = {x: s * (y - x), y: x * (r - z) - y, z: x * y - b * z}
    values = {s: p["sigma"], r: p["rho"], b: p["beta"]}
    return p, d, (x, y, z), rhs, values


def _lorenz_z(rng, noise, seed, sampling=None):
    p, d, (_, _, z), rhs, values = _lorenz(rng, noise, seed, sampling)
    return Draw("lorenz_z", p, d.t, d.x[:, :2], d.x_clean[:, :2], ("x", "y"),
                d.x_clean[:, 2:], {"rhs": rhs, "hidden": [z], "values": values},
                (("y", "x"),))


# ------------------------------------------- one hidden state in two equations
def _modulated(rng, noise, seed, sampling=None):
    p = {"omega": rng.uniform(1.0, 2.0), "k": rng.uniform(0.5, 1.5),
         "epsilon": rng.uniform(0.5, 1.5), "z0": rng.choice([-1, 1]) * rng.uniform(0.4, 0.8)}
    phase = rng.uniform(0, 2 * np.pi)
    d = systems.modulated_oscillator(omega=p["omega"], k=p["k"], epsilon=p["epsilon"],
                                     x0=(np.cos(phase), np.sin(phase), p["z0"]),
                                     t_end=40.0, n_times=2000, noise=noise, seed=seed,
                                     t=_times(sampling, 40.0))
    x, y, z = _sym("xyz")
    om, k, e = sp.symbols("omega k epsilon")
    rhs = {x: z * x - om * y, y: om * x + k * z * y, z: e * (1 - x**2 - y**2)}
    values = {om: p["omega"], k: p["k"], e: p["epsilon"]}
    return Draw("modulated", p, d.t, d.x[:, :2], d.x_clean[:, :2], ("x", "y"),
                d.x_clean[:, 2:], {"rhs": rhs, "hidden": [z], "values": values},
                (("x", "x"),))


# ------------------------------------------ several hidden states (issue 20's families)
def _simulated(rhs, x0, t, noise, seed):
    """Noise-free and noisy trajectories of ``rhs`` (noise as a share of each state's
    std, as in ``latentsindy.systems``)."""
    sol = solve_ivp(lambda _, s: rhs(s), (t[0], t[-1]), np.asarray(x0, float), t_eval=t,
                    method="DOP853", rtol=1e-10, atol=1e-10, max_step=(t[-1] - t[0]) / 200)
    if not sol.success:
        raise RuntimeError(f"simulation failed: {sol.message}")
    clean = sol.y.T
    rng = np.random.default_rng(seed)
    return clean, clean + noise * clean.std(axis=0) * rng.standard_normal(clean.shape)


def _grid(sampling, t_end):
    t = _times(sampling, t_end)
    return np.linspace(0.0, t_end, 2000) if t is None else t


def _lorenz_x(rng, noise, seed, sampling=None):
    """Lorenz seen through x alone: xdot = sigma (y - x) makes h0 = sigma y the
    coefficient of 1; h0's own equation has x's coefficient h1 = sigma (rho - z)."""
    p, d, (_, y, z), rhs, values = _lorenz(rng, noise, seed, sampling)
    return Draw("lorenz_x", p, d.t, d.x[:, :1], d.x_clean[:, :1], ("x",), d.x_clean[:, 1:],
                {"rhs": rhs, "hidden": [y, z], "values": values},
                (("x", "1"), ("h0", "x")), with_observed=True)


def _driven(rng, noise, seed, sampling=None):
    """A damped Duffing oscillator pushed by a hidden periodic drive u = F cos(w t + phi)
    (two hidden states: the drive and its rate; the drive is slower than the
    oscillator's own period)."""
    p = {"k": rng.uniform(0.8, 1.5), "c": rng.uniform(0.1, 0.3), "b": rng.uniform(0.5, 1.5),
         "force": rng.uniform(0.5, 1.2), "omega": rng.uniform(0.25, 0.45),
         "phase": rng.uniform(0, 2 * np.pi)}
    t_end = 5 * 2 * np.pi / p["omega"]
    t = _grid(sampling, t_end)
    u0 = p["force"] * np.cos(p["phase"])
    v0 = -p["force"] * p["omega"] * np.sin(p["phase"])
    x0 = (rng.uniform(-1.5, 1.5), rng.uniform(-1.0, 1.0), u0, v0)

    def rhs(s):
        x, y, u, v = s
        return [y, -p["k"] * x - p["c"] * y - p["b"] * x**3 + u, v, -p["omega"] ** 2 * u]

    clean, noisy = _simulated(rhs, x0, t, noise, seed)
    x, y, u, v = _sym("xyuv")
    k, c, b, w = sp.symbols("k c b omega")
    truth = {x: y, y: -k * x - c * y - b * x**3 + u, u: v, v: -w**2 * u}
    values = {k: p["k"], c: p["c"], b: p["b"], w: p["omega"]}
    return Draw("driven_oscillator", p, t, noisy[:, :2], clean[:, :2], ("x", "y"),
                clean[:, 2:], {"rhs": truth, "hidden": [u, v], "values": values},
                (("y", "1"), "rate"), with_observed=True)


def _epidemic(rng, noise, seed, sampling=None):
    """One SIR epidemic wave with only the infected fraction observed: Idot = h I with
    h = beta S - gamma, whose law is closed: hdot = -beta I (h + gamma)."""
    p = {"gamma": rng.uniform(0.1, 0.25), "r0": rng.uniform(1.8, 4.0),
         "infected": rng.uniform(0.001, 0.01)}
    p["beta"] = p["r0"] * p["gamma"]
    t_end = 12.0 / (p["gamma"] * (p["r0"] - 1.0) ** 0.5)
    t = _grid(sampling, t_end)

    def rhs(s):
        sus, inf = s
        return [-p["beta"] * sus * inf, p["beta"] * sus * inf - p["gamma"] * inf]

    clean, noisy = _simulated(rhs, (1.0 - p["infected"], p["infected"]), t, noise, seed)
    sus, inf = sp.Symbol("S", real=True), sp.Symbol("I", real=True)
    b, g = sp.symbols("beta gamma")
    truth = {sus: -b * sus * inf, inf: b * sus * inf - g * inf}
    values = {b: p["beta"], g: p["gamma"]}
    return Draw("epidemic", p, t, noisy[:, 1:], clean[:, 1:], ("I",), clean[:, :1],
                {"rhs": truth, "hidden": [sus], "values": values}, (("I", "I"),))


# ------------------------------------------- held-out systems (not in the default table)
def _vdp_simulated(rng, noise, seed, sampling):
    """Van der Pol, xdot = y, ydot = mu (1 - x^2) y - x (mu 0.5-2, about six cycles):
    (params, times, clean, noisy, truth, mu)."""
    p = {"mu": rng.uniform(0.5, 2.0)}
    phase = rng.uniform(0, 2 * np.pi)
    x0 = (2.0 * np.cos(phase), 2.0 * np.sin(phase))
    t_end = 6 * (2 * np.pi + 1.6 * p["mu"])  # about six cycles
    t = _grid(sampling, t_end)
    clean, noisy = _simulated(lambda s: [s[1], p["mu"] * (1 - s[0] ** 2) * s[1] - s[0]],
                              x0, t, noise, seed)
    x, y = _sym("xy")
    mu = sp.Symbol("mu")
    return p, t, clean, noisy, {x: y, y: mu * (1 - x**2) * y - x}, mu


def _van_der_pol(rng, noise, seed, sampling=None):
    """Van der Pol seen through x: xdot = y, ydot = mu (1 - x^2) y - x. The coefficient
    of 1 in dx/dt is y; with x and x^3 shown on their own it is the Lienard variable
    h = y - mu (x - x^3 / 3), whose law is hdot = -x."""
    p, t, clean, noisy, truth, mu = _vdp_simulated(rng, noise, seed, sampling)
    return Draw("van_der_pol", p, t, noisy[:, :1], clean[:, :1], ("x",), clean[:, 1:],
                {"rhs": truth, "hidden": [sp.Symbol("y", real=True)],
                 "values": {mu: p["mu"]}}, (("x", "1"),), with_observed=True)


def _brusselator(rng, noise, seed, sampling=None):
    """Brusselator seen through x: xdot = A - (B + 1) x + x^2 y, ydot = B x - x^2 y
    (a limit cycle: B > 1 + A^2); y is the coefficient of x^2 in dx/dt."""
    a = rng.uniform(0.8, 1.2)
    p = {"A": a, "B": 1 + a**2 + rng.uniform(0.5, 1.5)}
    x0 = (a * rng.uniform(0.5, 1.5), p["B"] / a * rng.uniform(0.5, 1.5))
    t_end = 40.0
    t = _grid(sampling, t_end)
    clean, noisy = _simulated(
        lambda s: [p["A"] - (p["B"] + 1) * s[0] + s[0] ** 2 * s[1],
                   p["B"] * s[0] - s[0] ** 2 * s[1]], x0, t, noise, seed)
    x, y = _sym("xy")
    sa, sb = sp.symbols("A B")
    truth = {x: sa - (sb + 1) * x + x**2 * y, y: sb * x - x**2 * y}
    return Draw("brusselator", p, t, noisy[:, :1], clean[:, :1], ("x",), clean[:, 1:],
                {"rhs": truth, "hidden": [y], "values": {sa: p["A"], sb: p["B"]}},
                (("x", "x^2"),), with_observed=True)


def _rossler(rng, noise, seed, sampling=None):
    """Rossler (non-spiking: a = b about 0.1, c about 4), x and y observed, z hidden:
    the coefficient of 1 in dx/dt is -y - z (or -z with -y shown on its own)."""
    p = {"a": rng.uniform(0.08, 0.12), "b": rng.uniform(0.08, 0.12),
         "c": rng.uniform(3.6, 4.4)}
    x0 = (rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(0, 0.5))
    t_end = 100.0
    t = _grid(sampling, t_end)
    clean, noisy = _simulated(
        lambda s: [-s[1] - s[2], s[0] + p["a"] * s[1], p["b"] + s[2] * (s[0] - p["c"])],
        x0, t, noise, seed)
    x, y, z = _sym("xyz")
    a, b, c = sp.symbols("a b c")
    truth = {x: -y - z, y: x + a * y, z: b + z * (x - c)}
    return Draw("rossler", p, t, noisy[:, :2], clean[:, :2], ("x", "y"), clean[:, 2:],
                {"rhs": truth, "hidden": [z], "values": {a: p["a"], b: p["b"], c: p["c"]}},
                (("x", "1"),), with_observed=True)


def _lv_predator(rng, noise, seed, sampling=None):
    """Lotka-Volterra seen through the predator y: the hidden prey x is the coefficient
    of y in dy/dt (h = d x - g, or d x with -g y shown on its own)."""
    p = {"a": rng.uniform(0.8, 1.2), "b": rng.uniform(0.08, 0.12),
         "g": rng.uniform(1.2, 1.8), "d": rng.uniform(0.06, 0.09)}
    x0 = (p["g"] / p["d"] * rng.uniform(0.4, 0.8), p["a"] / p["b"] * rng.uniform(0.4, 0.8))
    t = _grid(sampling, 20.0)
    clean, noisy = _simulated(lambda s: [p["a"] * s[0] - p["b"] * s[0] * s[1],
                                         -p["g"] * s[1] + p["d"] * s[0] * s[1]],
                              x0, t, noise, seed)
    x, y = _sym("xy")
    a, b, g, d = sp.symbols("a b g d")
    truth = {x: a * x - b * x * y, y: -g * y + d * x * y}
    return Draw("lv_predator", p, t, noisy[:, 1:], clean[:, 1:], ("y",), clean[:, :1],
                {"rhs": truth, "hidden": [x],
                 "values": {a: p["a"], b: p["b"], g: p["g"], d: p["d"]}},
                (("y", "y"),), with_observed=True)


def _duffing(rng, noise, seed, sampling=None):
    """A damped Duffing oscillator seen through x: xdot = v, vdot = -delta v - alpha x -
    beta x^3 (v hidden, the coefficient of 1 in dx/dt; its law needs x^3, beyond the
    default closure library's degree 2)."""
    p = {"delta": rng.uniform(0.05, 0.15), "alpha": rng.uniform(0.8, 1.2),
         "beta": rng.uniform(0.5, 1.5)}
    phase = rng.uniform(0, 2 * np.pi)
    x0 = (2.0 * np.cos(phase), 2.0 * np.sin(phase))
    t = _grid(sampling, 30.0)
    clean, noisy = _simulated(lambda s: [s[1], -p["delta"] * s[1] - p["alpha"] * s[0]
                                         - p["beta"] * s[0] ** 3], x0, t, noise, seed)
    x, v = _sym(["x", "v"])
    de, al, be = sp.symbols("delta alpha beta")
    truth = {x: v, v: -de * v - al * x - be * x**3}
    return Draw("duffing", p, t, noisy[:, :1], clean[:, :1], ("x",), clean[:, 1:],
                {"rhs": truth, "hidden": [v],
                 "values": {de: p["delta"], al: p["alpha"], be: p["beta"]}},
                (("x", "1"),), with_observed=True)


def _lorenz_y(rng, noise, seed, sampling=None):
    """Lorenz with x and z observed, y hidden: sigma y is the coefficient of 1 in dx/dt
    and y that of x in dz/dt (one hidden state seen through two terms)."""
    p = {"sigma": rng.uniform(9, 11), "rho": rng.uniform(26, 30),
         "beta": rng.uniform(2.4, 3.0)}
    x0 = [*rng.uniform(-10, 10, 2), rng.uniform(15, 30)]
    t = _grid(sampling, 10.0)
    clean, noisy = _simulated(lambda s: [p["sigma"] * (s[1] - s[0]),
                                         s[0] * (p["rho"] - s[2]) - s[1],
                                         s[0] * s[1] - p["beta"] * s[2]], x0, t, noise, seed)
    x, y, z = _sym("xyz")
    si, rh, be = sp.symbols("sigma rho beta")
    truth = {x: si * (y - x), y: x * (rh - z) - y, z: x * y - be * z}
    return Draw("lorenz_y", p, t, noisy[:, [0, 2]], clean[:, [0, 2]], ("x", "z"),
                clean[:, 1:2], {"rhs": truth, "hidden": [y],
                                "values": {si: p["sigma"], rh: p["rho"], be: p["beta"]}},
                (("x", "1"),), with_observed=True)



# ---------------------------- fresh held-out systems (added 2026-11-27, not developed on)
def _selkov(rng, noise, seed, sampling=None):
    """Sel'kov's glycolytic oscillator seen through x: xdot = -x + a y + x^2 y, ydot =
    b - a y - x^2 y (a limit cycle); y is the coefficient of x^2 in dx/dt (a y that of
    1, so one hidden state is seen through two terms of one equation)."""
    p = {"a": rng.uniform(0.06, 0.1), "b": rng.uniform(0.5, 0.7)}
    x0 = (rng.uniform(0.5, 1.5), rng.uniform(0.5, 1.5))
    t = _grid(sampling, 60.0)
    clean, noisy = _simulated(lambda s: [-s[0] + p["a"] * s[1] + s[0] ** 2 * s[1],
                                         p["b"] - p["a"] * s[1] - s[0] ** 2 * s[1]],
                              x0, t, noise, seed)
    x, y = _sym("xy")
    a, b = sp.symbols("a b")
    truth = {x: -x + a * y + x**2 * y, y: b - a * y - x**2 * y}
    return Draw("selkov", p, t, noisy[:, :1], clean[:, :1], ("x",), clean[:, 1:],
                {"rhs": truth, "hidden": [y], "values": {a: p["a"], b: p["b"]}},
                (("x", "x^2"),), with_observed=True)


def _competition(rng, noise, seed, sampling=None):
    """Two species competing for one resource, seen through x: xdot = x (1 - x - A y),
    ydot = r y (1 - y - B x), from small populations to coexistence (a transient); A y
    is the coefficient of x, whose law needs h^2."""
    p = {"A": rng.uniform(0.5, 0.9), "B": rng.uniform(0.5, 0.9), "r": rng.uniform(0.6, 1.5)}
    x0 = (rng.uniform(0.02, 0.1), rng.uniform(0.02, 0.1))
    t = _grid(sampling, 15.0)
    clean, noisy = _simulated(lambda s: [s[0] * (1 - s[0] - p["A"] * s[1]),
                                         p["r"] * s[1] * (1 - s[1] - p["B"] * s[0])],
                              x0, t, noise, seed)
    x, y = _sym("xy")
    sa, sb, r = sp.symbols("A B r")
    truth = {x: x * (1 - x - sa * y), y: r * y * (1 - y - sb * x)}
    return Draw("competition", p, t, noisy[:, :1], clean[:, :1], ("x",), clean[:, 1:],
                {"rhs": truth, "hidden": [y],
                 "values": {sa: p["A"], sb: p["B"], r: p["r"]}},
                (("x", "x"),), with_observed=True)


def _sprott_b(rng, noise, seed, sampling=None):
    """Sprott's chaotic system B, x and y observed: xdot = a y z, ydot = x - y, zdot =
    b - x y; z hidden, the coefficient of y in dx/dt (its law has no hidden term)."""
    p = {"a": rng.uniform(0.9, 1.1), "b": rng.uniform(0.9, 1.1)}
    x0 = rng.uniform(-1, 1, 3)
    t = _grid(sampling, 100.0)
    clean, noisy = _simulated(lambda s: [p["a"] * s[1] * s[2], s[0] - s[1],
                                         p["b"] - s[0] * s[1]], x0, t, noise, seed)
    x, y, z = _sym("xyz")
    a, b = sp.symbols("a b")
    truth = {x: a * y * z, y: x - y, z: b - x * y}
    return Draw("sprott_b", p, t, noisy[:, :2], clean[:, :2], ("x", "y"), clean[:, 2:],
                {"rhs": truth, "hidden": [z], "values": {a: p["a"], b: p["b"]}},
                (("x", "y"),), with_observed=True)


def _vdp_velocity(rng, noise, seed, sampling=None):
    """Van der Pol seen through its velocity y: ydot = mu (1 - x^2) y - x with x hidden,
    which enters through two terms, one of them nonlinearly (x^2 y)."""
    p, t, clean, noisy, truth, mu = _vdp_simulated(rng, noise, seed, sampling)
    return Draw("vdp_velocity", p, t, noisy[:, 1:], clean[:, 1:], ("y",), clean[:, :1],
                {"rhs": truth, "hidden": [sp.Symbol("x", real=True)],
                 "values": {mu: p["mu"]}}, (("y", "1"),), with_observed=True)


def _rayleigh(rng, noise, seed, sampling=None):
    """Rayleigh's oscillator seen through x: xdot = v, vdot = -x + mu (v - v^3) (a limit
    cycle); v is the coefficient of 1 in dx/dt, and its law needs v^3."""
    p = {"mu": rng.uniform(0.5, 1.5)}
    x0 = (rng.uniform(-2, 2), rng.uniform(-1, 1))
    t = _grid(sampling, 40.0)
    clean, noisy = _simulated(lambda s: [s[1], -s[0] + p["mu"] * (s[1] - s[1] ** 3)],
                              x0, t, noise, seed)
    x, v = _sym("xv")
    mu = sp.Symbol("mu")
    return Draw("rayleigh", p, t, noisy[:, :1], clean[:, :1], ("x",), clean[:, 1:],
                {"rhs": {x: v, v: -x + mu * (v - v**3)}, "hidden": [v],
                 "values": {mu: p["mu"]}}, (("x", "1"),), with_observed=True)


def _chen(rng, noise, seed, sampling=None):
    """Chen's chaotic system, x and y observed: xdot = a (y - x), ydot = (c - a) x - x z +
    c y, zdot = x y - b z; z hidden, the coefficient of x in dy/dt (fast: a about 35)."""
    p = {"a": rng.uniform(34.0, 36.0), "b": rng.uniform(2.8, 3.2), "c": rng.uniform(27.5, 28.5)}
    x0 = rng.uniform(-5, 5, 3)
    t = _grid(sampling, 10.0)
    clean, noisy = _simulated(
        lambda s: [p["a"] * (s[1] - s[0]), (p["c"] - p["a"]) * s[0] - s[0] * s[2]
                   + p["c"] * s[1], s[0] * s[1] - p["b"] * s[2]], x0, t, noise, seed)
    x, y, z = _sym("xyz")
    a, b, c = sp.symbols("a b c")
    truth = {x: a * (y - x), y: (c - a) * x - x * z + c * y, z: x * y - b * z}
    return Draw("chen", p, t, noisy[:, :2], clean[:, :2], ("x", "y"), clean[:, 2:],
                {"rhs": truth, "hidden": [z], "values": {a: p["a"], b: p["b"], c: p["c"]}},
                (("y", "x"),), with_observed=True)


def _rikitake(rng, noise, seed, sampling=None):
    """Rikitake's two-disc dynamo, x and y observed: xdot = -m x + z y, ydot = -m y +
    (z - A) x, zdot = 1 - x y (chaotic reversals); z hidden, the coefficient of y in
    dx/dt and of x in dy/dt."""
    p = {"m": rng.uniform(1.8, 2.2), "A": rng.uniform(4.5, 5.5)}
    x0 = (rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(2, 6))
    t = _grid(sampling, 100.0)
    clean, noisy = _simulated(lambda s: [-p["m"] * s[0] + s[2] * s[1],
                                         -p["m"] * s[1] + (s[2] - p["A"]) * s[0],
                                         1 - s[0] * s[1]], x0, t, noise, seed)
    x, y, z = _sym("xyz")
    m, sa = sp.symbols("m A")
    truth = {x: -m * x + z * y, y: -m * y + (z - sa) * x, z: 1 - x * y}
    return Draw("rikitake", p, t, noisy[:, :2], clean[:, :2], ("x", "y"), clean[:, 2:],
                {"rhs": truth, "hidden": [z], "values": {m: p["m"], sa: p["A"]}},
                (("x", "y"),), with_observed=True)


def _sprott_a(rng, noise, seed, sampling=None):
    """Sprott's system A (Nose-Hoover), x and y observed: xdot = y, ydot = -x + y z,
    zdot = a - y^2 (conservative chaos); z hidden, the coefficient of y in dy/dt."""
    p = {"a": rng.uniform(0.9, 1.1)}
    x0 = (0.0, rng.uniform(3.0, 5.0), 0.0)
    t = _grid(sampling, 100.0)
    clean, noisy = _simulated(lambda s: [s[1], -s[0] + s[1] * s[2], p["a"] - s[1] ** 2],
                              x0, t, noise, seed)
    x, y, z = _sym("xyz")
    a = sp.Symbol("a")
    truth = {x: y, y: -x + y * z, z: a - y**2}
    return Draw("sprott_a", p, t, noisy[:, :2], clean[:, :2], ("x", "y"), clean[:, 2:],
                {"rhs": truth, "hidden": [z], "values": {a: p["a"]}}, (("y", "y"),),
                with_observed=True)


def _hindmarsh_rose(rng, noise, seed, sampling=None):
    """Hindmarsh-Rose bursting neuron, x and y observed: xdot = y - x^3 + 3 x^2 - z + I,
    ydot = 1 - 5 x^2 - y, zdot = r (4 (x + 1.6) - z); the slow adaptation current z is
    hidden, the coefficient of 1 in dx/dt (with I)."""
    p = {"r": rng.uniform(0.01, 0.02), "I": rng.uniform(2.5, 3.2)}
    x0 = (rng.uniform(-1.5, 0.0), rng.uniform(-10.0, 0.0), rng.uniform(2.0, 3.0))
    t = _grid(sampling, 400.0)
    clean, noisy = _simulated(lambda s: [s[1] - s[0] ** 3 + 3 * s[0] ** 2 - s[2] + p["I"],
                                         1 - 5 * s[0] ** 2 - s[1],
                                         p["r"] * (4 * (s[0] + 1.6) - s[2])],
                              x0, t, noise, seed)
    x, y, z = _sym("xyz")
    r, current = sp.symbols("r I")
    truth = {x: y - x**3 + 3 * x**2 - z + current, y: 1 - 5 * x**2 - y,
             z: r * (4 * (x + sp.Rational(8, 5)) - z)}
    return Draw("hindmarsh_rose", p, t, noisy[:, :2], clean[:, :2], ("x", "y"), clean[:, 2:],
                {"rhs": truth, "hidden": [z], "values": {r: p["r"], current: p["I"]}},
                (("x", "1"),), with_observed=True)


# ------------------------------- a fourth batch (added 2026-11-27, run once as they came)
def _shimizu_morioka(rng, noise, seed, sampling=None):
    """Shimizu-Morioka's chaotic system, x and y observed: xdot = y, ydot = x - l y - x z,
    zdot = -a z + x^2; z hidden, the coefficient of x in dy/dt."""
    p = {"l": rng.uniform(0.7, 0.8), "a": rng.uniform(0.4, 0.45)}
    x0 = (rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(0.0, 1.0))
    t = _grid(sampling, 150.0)
    clean, noisy = _simulated(lambda s: [s[1], s[0] - p["l"] * s[1] - s[0] * s[2],
                                         -p["a"] * s[2] + s[0] ** 2], x0, t, noise, seed)
    x, y, z = _sym("xyz")
    sl, a = sp.symbols("l a")
    truth = {x: y, y: x - sl * y - x * z, z: -a * z + x**2}
    return Draw("shimizu_morioka", p, t, noisy[:, :2], clean[:, :2], ("x", "y"),
                clean[:, 2:], {"rhs": truth, "hidden": [z], "values": {sl: p["l"], a: p["a"]}},
                (("y", "x"),), with_observed=True)


def _rucklidge(rng, noise, seed, sampling=None):
    """Rucklidge's convection model, x and y observed: xdot = -k x + l y - y z, ydot = x,
    zdot = -z + y^2; z hidden, inside the coefficient of y in dx/dt."""
    p = {"k": rng.uniform(1.9, 2.1), "l": rng.uniform(6.5, 6.9)}
    x0 = (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(2.0, 6.0))
    t = _grid(sampling, 100.0)
    clean, noisy = _simulated(lambda s: [-p["k"] * s[0] + p["l"] * s[1] - s[1] * s[2], s[0],
                                         -s[2] + s[1] ** 2], x0, t, noise, seed)
    x, y, z = _sym("xyz")
    k, sl = sp.symbols("k l")
    truth = {x: -k * x + sl * y - y * z, y: x, z: -z + y**2}
    return Draw("rucklidge", p, t, noisy[:, :2], clean[:, :2], ("x", "y"), clean[:, 2:],
                {"rhs": truth, "hidden": [z], "values": {k: p["k"], sl: p["l"]}},
                (("x", "y"),), with_observed=True)


def _arneodo(rng, noise, seed, sampling=None):
    """Arneodo's jerk system, x and y observed: xdot = y, ydot = z, zdot = a x - b y - z
    - x^3; z hidden, the coefficient of 1 in dy/dt (its law needs x^3, beyond the default
    closure library)."""
    p = {"a": rng.uniform(5.0, 5.5), "b": rng.uniform(3.4, 3.6)}
    x0 = rng.uniform(-0.5, 0.5, 3)
    t = _grid(sampling, 100.0)
    clean, noisy = _simulated(lambda s: [s[1], s[2], p["a"] * s[0] - p["b"] * s[1] - s[2]
                                         - s[0] ** 3], x0, t, noise, seed)
    x, y, z = _sym("xyz")
    a, b = sp.symbols("a b")
    truth = {x: y, y: z, z: a * x - b * y - z - x**3}
    return Draw("arneodo", p, t, noisy[:, :2], clean[:, :2], ("x", "y"), clean[:, 2:],
                {"rhs": truth, "hidden": [z], "values": {a: p["a"], b: p["b"]}},
                (("y", "1"),), with_observed=True)


def _logistic_lv(rng, noise, seed, sampling=None):
    """Predator and prey with a logistic prey, seen through the prey: xdot = x (1 - x/K)
    - x y, ydot = -c y + b x y (damped cycles to coexistence); y is inside the
    coefficient of x."""
    p = {"K": rng.uniform(4.0, 8.0), "b": rng.uniform(0.6, 1.0), "c": rng.uniform(0.5, 1.0)}
    x0 = (rng.uniform(0.2, 0.5), rng.uniform(0.2, 0.5))
    t = _grid(sampling, 60.0)
    clean, noisy = _simulated(lambda s: [s[0] * (1 - s[0] / p["K"]) - s[0] * s[1],
                                         -p["c"] * s[1] + p["b"] * s[0] * s[1]],
                              x0, t, noise, seed)
    x, y = _sym("xy")
    sk, b, c = sp.symbols("K b c")
    truth = {x: x * (1 - x / sk) - x * y, y: -c * y + b * x * y}
    return Draw("logistic_lv", p, t, noisy[:, :1], clean[:, :1], ("x",), clean[:, 1:],
                {"rhs": truth, "hidden": [y], "values": {sk: p["K"], b: p["b"], c: p["c"]}},
                (("x", "x"),), with_observed=True)


FAMILIES = {
    f.name: f for f in [
        Family("lotka_volterra", "prey-only Lotka-Volterra (predator hidden)",
               lambda: ps.PolynomialLibrary(degree=3, include_bias=False), _lotka_volterra),
        Family("oscillator_logistic", "xdot = A y, ydot = B(t) x; B logistic, "
               "Bdot = r (B - lo)(hi - B)/(hi - lo)",
               lambda: ps.PolynomialLibrary(degree=2), _oscillator(True)),
        Family("oscillator_sinusoid", "xdot = A y, ydot = B(t) x; B sinusoidal, "
               "Bddot = -w^2 (B - b0) (two hidden states)",
               lambda: ps.PolynomialLibrary(degree=2), _oscillator(False)),
        Family("fitzhugh_nagumo", "FitzHugh-Nagumo, v observed: w is a hidden additive "
               "input with its own ODE", lambda: ps.PolynomialLibrary(degree=3),
               _fitzhugh_nagumo),
        Family("lorenz_z", "Lorenz, x and y observed: the hidden z multiplies x",
               lambda: ps.PolynomialLibrary(degree=2), _lorenz_z),
        Family("modulated", "oscillator with a hidden growth rate z entering both "
               "equations", lambda: ps.PolynomialLibrary(degree=2), _modulated),
        Family("lorenz_x", "Lorenz, x observed: y and z hidden (a hidden state inside "
               "another's equation)", lambda: ps.PolynomialLibrary(degree=2), _lorenz_x),
        Family("driven_oscillator", "damped Duffing oscillator pushed by a hidden "
               "periodic drive (drive and its rate hidden)",
               lambda: ps.PolynomialLibrary(degree=3), _driven),
        Family("epidemic", "one SIR wave, only the infected observed (susceptibles "
               "hidden, visited once)", lambda: ps.PolynomialLibrary(degree=2), _epidemic),
    ]
}


# Systems kept out of the default table and out of development: run them by name
# (``discovery.py --families van_der_pol brusselator rossler``) to check the defaults
# on systems they were not tuned on.
UNSEEN = {
    f.name: f for f in [
        Family("van_der_pol", "Van der Pol, x observed (y hidden; found in Lienard form)",
               lambda: ps.PolynomialLibrary(degree=3), _van_der_pol),
        Family("brusselator", "Brusselator, x observed (y hidden, the coefficient of "
               "x^2)", lambda: ps.PolynomialLibrary(degree=3), _brusselator),
        Family("rossler", "non-spiking Rossler, x and y observed (z hidden)",
               lambda: ps.PolynomialLibrary(degree=3), _rossler),
        # added later; duffing's draw 0 at 1% led to the check for a hidden state that is
        # a function of the observed states, so it is no longer unseen
        Family("lv_predator", "Lotka-Volterra seen through the predator (prey hidden)",
               lambda: ps.PolynomialLibrary(degree=3, include_bias=False), _lv_predator),
        Family("duffing", "damped Duffing oscillator, x observed (velocity hidden; its "
               "law needs x^3)", lambda: ps.PolynomialLibrary(degree=3), _duffing),
        Family("lorenz_y", "Lorenz, x and z observed (y hidden, seen through two terms)",
               lambda: ps.PolynomialLibrary(degree=2), _lorenz_y),
        # added 2026-11-27 and run once as they came, to check the defaults afresh
        Family("selkov", "Sel'kov glycolysis, x observed (y hidden, the coefficient of x^2 "
               "and, times a, of 1)", lambda: ps.PolynomialLibrary(degree=3), _selkov),
        Family("competition", "two competing species, x observed (y hidden; a transient "
               "to coexistence)", lambda: ps.PolynomialLibrary(degree=2, include_bias=False),
               _competition),
        Family("sprott_b", "Sprott's chaotic system B, x and y observed (z hidden)",
               lambda: ps.PolynomialLibrary(degree=2), _sprott_b),
        Family("vdp_velocity", "Van der Pol seen through its velocity (x hidden, also "
               "inside x^2 y)", lambda: ps.PolynomialLibrary(degree=3), _vdp_velocity),
        # added 2026-11-27 (a third batch), run once as they came
        Family("rayleigh", "Rayleigh's oscillator, x observed (velocity hidden; its law "
               "needs v^3)", lambda: ps.PolynomialLibrary(degree=3), _rayleigh),
        Family("chen", "Chen's chaotic system, x and y observed (z hidden)",
               lambda: ps.PolynomialLibrary(degree=2), _chen),
        Family("rikitake", "Rikitake's dynamo, x and y observed (z hidden, in both "
               "equations)", lambda: ps.PolynomialLibrary(degree=2), _rikitake),
        Family("sprott_a", "Sprott's system A (Nose-Hoover), x and y observed (z hidden)",
               lambda: ps.PolynomialLibrary(degree=2), _sprott_a),
        Family("hindmarsh_rose", "Hindmarsh-Rose bursting neuron, x and y observed (the "
               "slow current z hidden)", lambda: ps.PolynomialLibrary(degree=3),
               _hindmarsh_rose),
        # added 2026-11-27 (a fourth batch), run once as they came
        Family("shimizu_morioka", "Shimizu-Morioka's chaotic system, x and y observed (z "
               "hidden)", lambda: ps.PolynomialLibrary(degree=2), _shimizu_morioka),
        Family("rucklidge", "Rucklidge's convection model, x and y observed (z hidden)",
               lambda: ps.PolynomialLibrary(degree=2), _rucklidge),
        Family("arneodo", "Arneodo's jerk system, x and y observed (z hidden; its law "
               "needs x^3)", lambda: ps.PolynomialLibrary(degree=3), _arneodo),
        Family("logistic_lv", "predator and logistic prey, prey observed (predator "
               "hidden; damped cycles)",
               lambda: ps.PolynomialLibrary(degree=3, include_bias=False), _logistic_lv),
    ]
}
ALL_FAMILIES = {**FAMILIES, **UNSEEN}


def draw(family: str, index: int, noise: float, sampling=None) -> Draw:
    """Draw ``index`` of ``family`` (parameters depend on the index only, not the noise
    or the sampling). ``sampling(t_end)`` gives the sample times (default 2000 equally
    spaced ones from 0 to the family's ``t_end``)."""
    rng = np.random.default_rng([_seed(family), index])
    return ALL_FAMILIES[family].draw(rng, noise, 1000 + index, sampling)


def _seed(name: str) -> int:
    return sum((k + 1) * ord(ch) for k, ch in enumerate(name))
