"""Stage one's exact check: the varying-coefficient model on the whole data.

:class:`VaryingCoefficients` sets the model up once per fit (integral-form normal
equations, :mod:`.vcm`; one :class:`~.vcm_fit.EquationModel` per equation) and
answers the two questions stage one asks of it: which structure each equation has
(:meth:`choose`, by :mod:`.structure`) and what the posterior of a structure's
coefficients is (:meth:`fit`, :meth:`series`).

Resolution: knots every half differentiator window in time (the finest scale the
noise lets the data resolve; the window is chosen by the discrepancy principle, so
short on clean data, wide on noisy data), at most ``MAX_KNOTS`` over the series;
integration windows of four half differentiator windows (four knot spacings where the
knots are not capped).
"""

from __future__ import annotations

import numpy as np

from .._core.budget import expired, left_out, passed
from .._core.derivatives import choose_window
from .._core.threads import one_blas_thread
from .._core.timing import timed
from .structure import GAUSSIAN, EquationChoice, StructureSearch
from .vcm import LevelGram, spline_basis
from .vcm_fit import EquationFit, EquationModel

MAX_KNOTS = 1024
MIN_KNOTS = 16
NOISE_FLOOR = 1e-3  # measurement noise floor, relative to each state's std


def resolution(x: np.ndarray, t: np.ndarray, noise_std=None) -> tuple[int, int]:
    """(number of knots, samples per integration window) for a trajectory (the
    differentiator's windows at the states' noise levels ``noise_std``, estimated from
    ``x`` when not given)."""
    n = len(t)
    sigmas = [None] * x.shape[1] if noise_std is None else [float(s) for s in noise_std]
    windows = [choose_window(x[:, j], t=t, sigma=sigmas[j]) for j in range(x.shape[1])]
    half = max(1.0, min(windows) / 2.0)  # samples between knots
    n_knots = int(np.clip(round((n - 1) / half) + 3, MIN_KNOTS, MAX_KNOTS))
    step = (n - 1) / (n_knots - 3)  # samples between knots after the clip
    # windows of four knot spacings, but never longer than four half differentiator
    # windows: where MAX_KNOTS spreads the knots (long series) a window of four spacings
    # would integrate the noise of the library's states over thousands of samples, an
    # error the model (noise on the states only) does not have (10^6 Lorenz samples:
    # misfit 6-11 times the noise, rho 0.6% low, with 4000-sample windows)
    return n_knots, max(4, int(round(4 * min(step, half))))


class VaryingCoefficients:
    """The varying-coefficient model of every equation of one fit.

    Parameters
    ----------
    trajectories : list of (n, S) arrays sharing one clock (``times``)
    times : list of (n,) arrays
    thetas : list of (n, F) arrays, the library divided by ``feature_scale``
    derivative_scale : (S,) array: the normalisation of each equation
    noise_std : (S,) array: the measurement noise of each state
    noise_correlation : (S,) array, optional
        Its correlation between neighbouring samples (AR(1); default white). An
        equation whose state's noise is correlated gets normal equations whitened for
        it (:class:`~.vcm.LevelGram`; one set per distinct correlation).
    """

    @timed("stage one: exact model")
    def __init__(self, trajectories, times, thetas, derivative_scale, noise_std,
                 noise_correlation=None):
        t0 = min(float(t[0]) for t in times)
        t1 = max(float(t[-1]) for t in times)
        longest = int(np.argmax([len(t) for t in times]))
        n_states = len(derivative_scale)
        phi = (np.zeros(n_states) if noise_correlation is None
               else np.asarray(noise_correlation, float))
        floor = NOISE_FLOOR * np.std(np.vstack(trajectories), axis=0)
        noise = np.maximum(np.asarray(noise_std, float), floor)
        self.n_knots, self.window = resolution(
            trajectories[longest], times[longest], noise if np.any(phi > 0) else None)
        self.span = (t0, t1)
        states = [np.asarray(x, float) / derivative_scale for x in trajectories]
        grams = {p: LevelGram(states, times, thetas, self.n_knots, self.span, self.window, p)
                 for p in sorted(set(phi.tolist()))}
        noise = noise / derivative_scale
        self.models = [EquationModel(grams[float(phi[i])].equation(i), noise[i] ** 2)
                       for i in range(n_states)]
        self.basis = spline_basis(times[longest], self.n_knots, self.span)

    def basis_at(self, times):
        """The spline basis at other times (for :meth:`EquationFit.series`)."""
        return spline_basis(np.asarray(times, float), self.n_knots, self.span)

    @timed("stage one: exact model")
    def choose(self, support, varying, free_rows, allowed, threshold):
        """The structure of every equation, by evidence (``structure`` module).

        ``support``, ``varying``, ``allowed``: (S, F) bool arrays (the generator's
        proposal; the terms that may vary); ``free_rows``: equations whose support is
        free. Returns one :class:`EquationChoice` per equation (None for an equation
        with an empty fixed support).
        """
        with one_blas_thread():  # small dense algebra: threads cost more than they gain
            return self._choose(support, varying, free_rows, allowed, threshold)

    def _choose(self, support, varying, free_rows, allowed, threshold):
        out = []
        for i, model in enumerate(self.models):
            sup = set(np.flatnonzero(support[i]))
            var = set(np.flatnonzero(varying[i] & support[i]))
            free = bool(free_rows[i])
            if not free and not sup:
                out.append(None)
                continue
            search = StructureSearch(model, self.basis, threshold, free, sup,
                                     set(np.flatnonzero(allowed[i])),
                                     f"equation {i + 1} of {len(self.models)}")
            starts = [(sup, var), (sup, set())]
            if free:
                starts.append((thresholded_constants(model.g, threshold,
                                                     range(model.g.n_features)), set()))
            out.append(search.run(starts, proposed=sup))
        return out

    def fit(self, i, support_row, varying_row) -> EquationFit:
        """Posterior of one equation's structure (adaptive slope priors; Gaussian ones
        where the discovery's ``max_time`` has run out, or the structure search left
        them out for it, and the adaptive fit is not at hand)."""
        support = np.flatnonzero(support_row)
        varying = np.flatnonzero(np.asarray(varying_row) & support_row)
        adaptive = (not (expired() or left_out(GAUSSIAN))
                    or self.models[i].fitted(support, varying, True))
        if not adaptive:
            passed(GAUSSIAN)
        return self.models[i].fit(support, varying, adaptive=adaptive)


def thresholded_constants(gram, threshold, candidates):
    """Support of a sequentially thresholded least-squares fit with constant
    coefficients (STLSQ on the integral form), among ``candidates``."""
    active = sorted(candidates)
    for _ in range(len(active) + 1):
        if not active:
            break
        g = gram.const[np.ix_(active, active)]
        coef = np.linalg.lstsq(g, gram.const_y[active], rcond=None)[0]
        keep = [j for j, c in zip(active, coef, strict=True) if abs(c) >= threshold]
        if keep == active:
            break
        active = keep
    return set(active)


__all__ = ["EquationChoice", "VaryingCoefficients", "resolution"]
