"""Coefficient shapes: small frozen callables of time (re-exported by ``systems``)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Constant:
    """A coefficient that does not change: ``value`` for all t."""

    value: float

    def __call__(self, t):
        return np.full_like(np.asarray(t, dtype=float), self.value)


@dataclass(frozen=True)
class Switch:
    """One abrupt switch from ``before`` to ``after`` at time ``at``."""

    before: float
    after: float
    at: float

    def __call__(self, t):
        return np.where(np.asarray(t, dtype=float) < self.at, self.before, self.after)


@dataclass(frozen=True)
class Switches:
    """Several switches: ``values[k]`` holds on ``[times[k-1], times[k])``."""

    values: tuple[float, ...]
    times: tuple[float, ...]

    def __post_init__(self):
        if len(self.values) != len(self.times) + 1:
            raise ValueError(
                f"Switches needs one more value than switch times; got {len(self.values)} "
                f"values and {len(self.times)} times."
            )
        if np.any(np.diff(self.times) <= 0):
            raise ValueError(f"Switch times must increase strictly; got {self.times}.")

    def __call__(self, t):
        index = np.searchsorted(np.asarray(self.times), np.asarray(t, dtype=float), side="right")
        return np.asarray(self.values, dtype=float)[index]


@dataclass(frozen=True)
class Sigmoid:
    """Logistic transition ``low + (high - low) / (1 + exp(-sharpness (t - at)))``."""

    low: float
    high: float
    at: float
    sharpness: float = 1.0

    def __call__(self, t):
        arg = -self.sharpness * (np.asarray(t, dtype=float) - self.at)
        return self.low + (self.high - self.low) / (1.0 + np.exp(np.clip(arg, -700, 700)))


@dataclass(frozen=True)
class Sinusoid:
    """``offset + amplitude sin(2 pi frequency t + phase)``."""

    offset: float
    amplitude: float
    frequency: float
    phase: float = 0.0

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        return self.offset + self.amplitude * np.sin(2 * np.pi * self.frequency * t + self.phase)


@dataclass(frozen=True)
class FourierSeries:
    """``offset + sum_k amplitudes[k] sin(2 pi frequencies[k] t + phases[k])``."""

    offset: float
    amplitudes: tuple[float, ...]
    frequencies: tuple[float, ...]
    phases: tuple[float, ...] = field(default=())

    def __call__(self, t):
        t = np.asarray(t, dtype=float)
        phases = self.phases or (0.0,) * len(self.amplitudes)
        out = np.full_like(t, self.offset)
        for a, f, p in zip(self.amplitudes, self.frequencies, phases, strict=True):
            out = out + a * np.sin(2 * np.pi * f * t + p)
        return out
