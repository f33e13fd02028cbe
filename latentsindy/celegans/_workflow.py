"""The seed paper's C. elegans workflow, made to recover what it claims to.

1. The first principal component x of each worm, and y = xdot (noise-adaptive
   Savitzky-Golay).
2. Stage one (the paper): dynamic SINDy with the fixed structure ``xdot = y``,
   ``ydot = a x^3 + b x^2 + c x + d y + u(t)``, only u varying. Its u(t) is the raw input.
3. u(t) becomes a two-level switch (:func:`two_level_switch`).
4. With a free u(t), stage one's constants are not identified: any error in the cubic is
   absorbed by u (on the paper's system they come out 2-3x off). Once u is a two-level
   switch they are, so the constants and the levels are refitted in weak form, u is
   re-read through the refitted model, re-segmented, and so on until the switch stops
   moving. Several worms share the constants and keep their own levels and switches.
5. The model is integrated under the switch (torchdiffeq) and compared with the data;
   the fixed points of each level and their stability are reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pysindy as ps
import sympy as sp

from .._core.derivatives import rate
from .._stage_one.estimator import DynamicSINDy
from ._dynamics import ORDER, FixedPoint, fixed_points, nrmse, simulate
from ._plots import plot_model
from ._recording import Component, WormRecording
from ._switch import Switch, sigmoid_switch, two_level_switch
from ._weak import fit_shared, half_width, local_input

SUPPORT = {"x": ["y"], "y": ["1", "x", "x^2", "x^3", "y"]}
TIME_VARYING = {"y": ["1"]}


@dataclass(frozen=True)
class WormFit:
    """One worm under the shared model.

    Attributes
    ----------
    name : str
    t, x, y : ndarray (n_frames,)
        Frame times, first component and its derivative.
    raw_u, raw_u_std : ndarray (n_frames,)
        Stage one's input (dynamic SINDy's varying constant) and its posterior spread;
        the weak-form estimate with a constant start when stage one was skipped (std 0).
    sigmoid_u : ndarray (n_frames,)
        The paper's sigmoid recipe applied to ``raw_u`` (for comparison).
    input_u : ndarray (n_frames,)
        u(t) read through the final constants (what the final switch segments).
    switch : Switch
        The final two-level input, levels from the joint fit.
    free_run : ndarray (n_frames,)
        The model's x integrated under the switch from the data's state at the first
        frame (NaN after a blow-up).
    nrmse_free : float
        Its RMS error over the standard deviation of x. Orbits that pass near the saddle
        make this sensitive: on the paper's own model, 0.5% error in every coefficient
        takes it from 0.04 to 0.68 (see the README).
    fixed_points : tuple of (level, tuple of FixedPoint)
    explained : float
        Variance fraction of the first component (nan if x was given directly).
    """

    name: str
    t: np.ndarray = field(repr=False)
    x: np.ndarray = field(repr=False)
    y: np.ndarray = field(repr=False)
    raw_u: np.ndarray = field(repr=False)
    raw_u_std: np.ndarray = field(repr=False)
    sigmoid_u: np.ndarray = field(repr=False)
    input_u: np.ndarray = field(repr=False)
    switch: Switch
    free_run: np.ndarray = field(repr=False)
    nrmse_free: float
    fixed_points: tuple
    explained: float


@dataclass(frozen=True)
class SwitchingModel:
    """``xdot = y``, ``ydot = a x^3 + b x^2 + c x + d y + u_worm(t)``, u a two-level switch.

    Attributes
    ----------
    cubic, cubic_std : dict
        Shared coefficients of ``x^3, x^2, x, y`` and their standard errors (from the
        weak-form regression, inflated for the overlap of its test functions; noise in
        x also biases them, by about ``3 a sigma^2`` for the x coefficient).
    stage_one_cubic : tuple of dict
        Each worm's constants from stage one alone (free u), for comparison.
    worms : tuple of WormFit
    half_width : int
        Weak-form test-function half-width (samples).
    rounds : int
        Refit/re-segment rounds used; ``converged`` says whether the switch settled.
    converged : bool
    """

    cubic: dict
    cubic_std: dict
    stage_one_cubic: tuple
    worms: tuple
    half_width: int
    rounds: int
    converged: bool

    def equations(self):
        """Sympy equations ``(xdot, ydot)``; each worm's input is the symbol ``u``."""
        x, y, u = sp.symbols("x y u")
        powers = {"x^3": x**3, "x^2": x**2, "x": x, "y": y}
        rhs = sum((sp.Float(self.cubic[k], 4) * powers[k] for k in ORDER), u)
        fx, fy = sp.Function("x"), sp.Function("y")
        t = sp.Symbol("t")
        return (sp.Eq(fx(t).diff(t), y), sp.Eq(fy(t).diff(t), rhs))

    def summary(self) -> str:
        terms = " ".join(f"{self.cubic[k]:+.4g}*{k}" for k in ORDER)
        lines = ["Switching cubic (shared by all worms):", "  xdot = y",
                 f"  ydot = {terms} + u(t)"]
        lines.append("  standard errors: " + ", ".join(
            f"{k} {self.cubic_std[k]:.2g}" for k in ORDER))
        if not self.converged:
            lines.append(f"  NOT CONVERGED: the switch still moved after {self.rounds} rounds.")
        for w in self.worms:
            lo, hi = w.switch.levels
            lines.append(f"{w.name}: u in {{{lo:.4g}, {hi:.4g}}}, "
                         f"{w.switch.switch_times.size} switches; closed-system NRMSE "
                         f"{w.nrmse_free:.3g} from the first frame")
            for level, points in w.fixed_points:
                desc = ", ".join(f"{p.x:.3g} ({p.kind})" for p in points)
                lines.append(f"    u = {level:.4g}: fixed points {desc}")
        return "\n".join(lines)

    def plot(self, path=None, *, truth=None):
        """Data vs model, the input and its switch, and the nullclines with fixed points
        (see :func:`latentsindy.celegans.plot_model`)."""
        return plot_model(self, path=path, truth=truth)


def fit_switching_model(data, *, stage_one: bool = True, training=None, center: bool = False,
                        test_half_width: int | None = None, penalty: float | None = None,
                        max_rounds: int = 30, seed: int = 0,
                        verbose: bool = False) -> SwitchingModel:
    """Fit the paper's switching cubic to one or several worms.

    Parameters
    ----------
    data : WormRecording, Component, or a list of them
        Recordings (their first principal component is used) or components.
    stage_one : bool
        Read the raw input with dynamic SINDy (the paper's route). ``False`` starts
        from the weak-form input under a constant-u fit instead (faster: no training).
    training : TrainingOptions or dict, optional
        Stage one's training options.
    center : bool
        Passed to :meth:`WormRecording.first_component`.
    test_half_width : int, optional
        Weak-form test-function half-width in samples (default: from the spectrum of x).
    penalty : float, optional
        Switch penalty of :func:`two_level_switch` (default: BIC).
    max_rounds : int
        Limit on refit/re-segment rounds.
    seed : int
    verbose : bool

    Returns
    -------
    SwitchingModel
    """
    items = list(data) if isinstance(data, list | tuple) else [data]
    if not items:
        raise ValueError("data is empty; pass a WormRecording, a Component or a list.")
    if max_rounds < 1:
        raise ValueError(f"max_rounds must be >= 1; got {max_rounds}.")
    comps = [_component(item, center) for item in items]
    ys = [rate(c.x[:, None], c.t)[0][:, 0] for c in comps]
    dts = [float(np.median(np.diff(c.t))) for c in comps]
    if test_half_width is not None and (not isinstance(test_half_width, int | np.integer)
                                        or test_half_width < 2):
        raise ValueError(f"test_half_width must be an int >= 2 (samples); got "
                         f"{test_half_width!r}.")
    m = test_half_width or int(np.median([half_width(c.x) for c in comps]))
    short = min(c.x.size for c in comps)
    if short < 4 * m + 2:
        raise ValueError(f"test functions of half-width {m} samples need at least "
                         f"{4 * m + 2} frames per worm; the shortest worm has {short}. "
                         "Pass a smaller test_half_width.")
    raw, raw_std, stage_cubic = [], [], []
    for c, y, dt in zip(comps, ys, dts, strict=True):
        u, s, cubic = (_stage_one(c, y, training, seed, verbose) if stage_one
                       else _constant_start(c, dt, m))
        raw.append(u)
        raw_std.append(s)
        stage_cubic.append(cubic)
    switches = [two_level_switch(u, c.t, penalty=penalty) for u, c in zip(raw, comps,
                                                                           strict=True)]
    converged, rounds = False, 0
    for rounds in range(1, max_rounds + 1):  # noqa: B007 - rounds is reported
        consts, levels, se, inputs = _refit(comps, switches, dts, m)
        new = [two_level_switch(u, c.t, penalty=penalty) for u, c in zip(inputs, comps,
                                                                         strict=True)]
        if all(np.array_equal(a.labels, b.labels) for a, b in zip(new, switches,
                                                                   strict=True)):
            converged = True
            break
        switches = new
    if not converged:  # constants, levels and inputs of the switch that is reported
        consts, levels, se, inputs = _refit(comps, switches, dts, m)
    cubic = dict(zip(ORDER, (float(v) for v in consts), strict=True))
    cubic_std = dict(zip(ORDER, (float(v) for v in se), strict=True))
    worms = []
    for i, c in enumerate(comps):
        labels, lv = switches[i].labels, levels[i].copy()
        if lv[0] > lv[1]:  # label 0 is the low level
            labels, lv = 1 - labels, lv[::-1].copy()
        sw = Switch(c.t, labels, lv, switches[i].penalty)
        free = simulate(cubic, sw, c.t, c.x, ys[i])
        points = tuple((float(lv), fixed_points(cubic, float(lv))) for lv in sw.levels)
        worms.append(WormFit(c.name, c.t, c.x, ys[i], raw[i], raw_std[i],
                             sigmoid_switch(raw[i]), inputs[i], sw, free,
                             nrmse(free, c.x), points, c.explained))
    return SwitchingModel(cubic, cubic_std, tuple(stage_cubic), tuple(worms), m, rounds,
                          converged)


def _refit(comps, switches, dts, m):
    """Shared constants and per-worm levels under the switches, and u(t) read through
    them."""
    consts, levels, se, _ = fit_shared([c.x for c in comps], [s.labels for s in switches],
                                       dts, m)
    inputs = [local_input(c.x, dt, consts, m) for c, dt in zip(comps, dts, strict=True)]
    return consts, levels, se, inputs


def _component(item, center) -> Component:
    if isinstance(item, WormRecording):
        return item.first_component(center=center)
    if isinstance(item, Component):
        return item
    raise TypeError(f"expected a WormRecording or a Component; got {type(item).__name__}. "
                    "Load files with latentsindy.celegans.load_kato, or wrap traces you "
                    "have: WormRecording(name, t, traces, neuron_names, fps).")


def _stage_one(comp, y, training, seed, verbose):
    model = DynamicSINDy(ps.PolynomialLibrary(degree=3), support=SUPPORT,
                         time_varying=TIME_VARYING, training=training, seed=seed,
                         verbose=verbose)
    model.fit(np.column_stack([comp.x, y]), comp.t, feature_names=["x", "y"])
    coef = model.coefficients()
    cubic = {k: float(np.mean(coef.term("y", k))) for k in ORDER}
    return coef.term("y", "1").copy(), coef.term_std("y", "1").copy(), cubic


def _constant_start(comp, dt, m):
    labels = np.zeros(comp.x.size, dtype=int)
    consts, _, _, _ = fit_shared([comp.x], [labels], [dt], m)
    u = local_input(comp.x, dt, consts, m)
    return u, np.zeros_like(u), dict(zip(ORDER, (float(v) for v in consts), strict=True))


__all__ = ["FixedPoint", "SwitchingModel", "WormFit", "fit_switching_model"]
