"""The seed paper's synthetic experiments (main text 4.1-4.3, 4.6): cases and truth.

Oscillator (main text eq. 2): ``xdot = A(t) y``, ``ydot = B(t) x``, t in [0, 25],
2000 samples. Lorenz with one of sigma, rho, beta varying, t in [0, 20] at 2000
samples (timeVAE) or [0, 100] at 10,000 samples (dynamic HyperSINDy), dt = 0.01.
Shapes are placed relative to the series length so the long runs see the same
variation, stretched. Noise: 1% of each state's standard deviation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from latentsindy import systems

S = systems
NOISE = 0.01
OSC_T_END, OSC_N = 25.0, 2000
LORENZ_N = {"timevae": 2000, "hypersindy": 10_000}
LORENZ_DT = 0.01
# frequencies (cycles per series) of the 7-term Fourier series, and its amplitudes
FOURIER_CYCLES = (1, 2, 3, 4, 5, 6, 7)
FOURIER_SHARES = (0.35, 0.25, 0.2, 0.15, 0.12, 0.1, 0.08)


@dataclass(frozen=True)
class Case:
    """One experiment: a system, which parameter varies and how."""

    system: str  # "oscillator" or "lorenz"
    shape: str  # "switch", "switches", "sigmoid", "sinusoid(s)", "fourier"
    parameters: dict = field(default_factory=dict)  # name -> (low, high) or constants
    generator: str = "timevae"

    @property
    def name(self) -> str:
        varying = "+".join(self.parameters)
        tag = "" if self.generator == "timevae" else " (T=10k)"
        return f"{self.system} {varying} {self.shape}{tag}"


def _shape(shape, low, high, t_end, *, cycles=1.0):
    """A coefficient moving between ``low`` and ``high`` over a series of length t_end."""
    mid, amp = 0.5 * (low + high), 0.5 * (high - low)
    if shape == "switch":
        return S.Switch(low, high, at=0.5 * t_end)
    if shape == "switches":  # alternating, four switches
        times = tuple(t_end * k / 5 for k in range(1, 5))
        return S.Switches(tuple(low if k % 2 == 0 else high for k in range(5)), times)
    if shape == "sigmoid":  # 10-90% rise over 44% of the series (smooth, as in the tests)
        return S.Sigmoid(low, high, at=0.5 * t_end, sharpness=10.0 / t_end)
    if shape.startswith("sinusoid"):
        return S.Sinusoid(mid, amp, cycles / t_end)
    if shape == "fourier":
        scale = amp / sum(FOURIER_SHARES)
        return S.FourierSeries(mid, tuple(scale * a for a in FOURIER_SHARES),
                               tuple(c / t_end for c in FOURIER_CYCLES),
                               tuple(0.7 * c for c in FOURIER_CYCLES))
    raise ValueError(shape)


def true_switch_times(case: Case, t_end: float) -> np.ndarray | None:
    if case.shape == "switch" or case.shape == "sigmoid":
        return np.array([0.5 * t_end])
    if case.shape == "switches":
        return np.array([t_end * k / 5 for k in range(1, 5)])
    return None


def true_labels(case: Case, t: np.ndarray) -> np.ndarray | None:
    times = true_switch_times(case, float(t[-1]))
    if times is None:
        return None
    return (np.searchsorted(times, t, side="right") % 2).astype(int)


OSC_RANGES = {"A": (-1.0, -4.0), "B": (1.0, 3.0)}
LORENZ_RANGES = {"sigma": (8.0, 14.0), "rho": (24.0, 34.0), "beta": (2.0, 3.5)}


def oscillator_cases():
    cases = [Case("oscillator", s, {"A": OSC_RANGES["A"]})
             for s in ("switch", "switches", "sigmoid")]
    cases.append(Case("oscillator", "sinusoids", {"A": OSC_RANGES["A"], "B": OSC_RANGES["B"]}))
    cases.append(Case("oscillator", "fourier", {"A": OSC_RANGES["A"]}))
    return cases


def lorenz_cases(generator="timevae"):
    return [Case("lorenz", s, {p: LORENZ_RANGES[p]}, generator)
            for p in ("sigma", "rho", "beta") for s in ("sigmoid", "switch", "sinusoid", "fourier")]


def make_data(case: Case, seed: int = 0):
    """(SystemData, t_end) for a case."""
    if case.system == "oscillator":
        t_end = OSC_T_END
        cycles = {"A": 2.0, "B": 5.0}  # two sinusoids of different frequency
        kw = {"A": -1.0, "B": 1.0}
        kw.update({p: _shape(case.shape, lo, hi, t_end, cycles=cycles[p])
                   for p, (lo, hi) in case.parameters.items()})
        return systems.harmonic_oscillator(**kw, t_end=t_end, n_times=OSC_N, noise=NOISE,
                                           seed=seed), t_end
    n = LORENZ_N[case.generator]
    t_end = LORENZ_DT * n
    kw = {p: _shape(case.shape, lo, hi, t_end, cycles=2.0)
          for p, (lo, hi) in case.parameters.items()}
    return systems.lorenz(**kw, t_end=t_end, n_times=n, noise=NOISE, seed=seed), t_end


def varying_terms(case: Case, data) -> dict:
    """(state, feature) -> true series, for the terms whose coefficient varies."""
    return {k: v for k, v in data.terms.items() if np.ptp(v) > 0}


def constant_terms(data) -> dict:
    return {k: float(v[0]) for k, v in data.terms.items() if np.ptp(v) == 0 and v[0] != 0}
