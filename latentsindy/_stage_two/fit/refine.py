"""Closed-loop refinement: fit a closed system to the observed series by integrating it.

The free coefficients and every segment's start (observed and hidden states) are
estimated by Levenberg-Marquardt on the multiple-shooting residuals
(:mod:`.shooting`): observed samples in units of their noise level, and
the gaps between consecutive segments, weighted so that at the solution they are a
small fraction of the noise (continuity is enforced by a penalty that is raised until
it holds). Only the observed states enter the misfit, so the hidden states are
whatever the closed system needs them to be. A hidden state's continuity unit comes
from the initial guess, and the state can shrink below it (its loadings growing) and
then jump between segments by its whole variation while the gaps read small:
:meth:`Problem.joins` measures such jumps in the state's own spread, and a fit that
does not join is no trajectory of its system.

Held-out scoring: :mod:`.held_out`.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
import torch

from ..._core.coloured import with_ar1
from ..._core.derivatives import measurement_noise
from ..._core.oscillation import crossing_periods
from ..context import NOISE_FLOOR
from .batches import make_batches, run_groups
from .data_rows import data_rows, sample_weights, sum_of_squares
from .field import ParametricSystem
from .least_squares import RESOLUTION, GiveUpWatch, covariance, levenberg_marquardt
from .least_squares import degrees_of_freedom as _dof
from .normal_equations import NormalEquations, as_array
from .shooting import Integrator, make_groups, stable_step
from .whiten import carry_over, whiten

_GAP = 1e-2  # continuity gaps are held below this fraction of the noise level
MAX_GRID = 400  # integrator steps per segment at most
_PENALTY = (1e2, 1e4)  # continuity weight: first pass, then the enforcing pass
# A hidden state's jump at a segment boundary above this fraction of its own spread over
# the data is a break in the trajectory, not a gap left by the penalty (segments that
# join leave jumps below 1e-3 of it; shrunk piecewise-constant states jump by 0.5-2x it).
JOIN = 0.05
# Segments whose ends lie further than this from the next segment's start (largest
# continuity gap, in noise levels) are no trajectory of their system: the continuity
# penalty aims below _GAP, and a right system's fit meets it. A fit left with gaps of a
# noise level or more is one the closed system cannot follow (Hindmarsh-Rose at 1%
# noise, draws 0 and 3: gaps of 11 and 12 noise levels, misfits of 900-2,200 noise
# variances), and checks that refit it would measure the fit's tearing, not its terms.
CONTINUOUS = 1.0


@dataclass(frozen=True)
class RefineOptions:
    """How the closed system is fitted by integration (defaults are unit-free).

    Attributes
    ----------
    segment_samples : (int, int)
        Smallest and largest segment length in samples (of the median step over all
        samples); within it, an eighth of the observed series' dominant period. Short
        segments keep a chaotic system's segments close to the data from the first
        iteration (100-sample segments did not converge on Lorenz at 5% noise) and
        cost no more: segments are integrated side by side. The smallest is 8 samples:
        sampled 12 times per cycle, 16-sample segments left 4 held-out segments on
        prey-only Lotka-Volterra, too few for the score to tell systems apart (a wrong
        law won, confident); 8 leaves 7.
    max_iterations : int
        Levenberg-Marquardt iterations per pass.
    n_folds : int
        Interleaved folds of held-out segments for the score.
    device : str
        Torch device of the integrations ("cpu" or "cuda"); the normal equations are
        solved on the CPU.
    noise : tuple of float, optional
        Measurement noise standard deviation of each observed state, the unit of every
        misfit and score; None (default): estimated from the data
        (:func:`latentsindy._core.derivatives.measurement_noise`). The judge sets it
        from its best fit where the data's estimate was too high (sparse samples).
    """

    segment_samples: tuple[int, int] = (8, 50)
    max_iterations: int = 40
    n_folds: int = 4
    device: str = "cpu"
    noise: tuple | None = None


@dataclass(frozen=True)
class Fit:
    """A refined closed system and how it was obtained."""

    system: ParametricSystem
    starts: np.ndarray  # (n_segments, n_states)
    cost: float
    data_cost: float
    n_data: int
    gap: float  # largest continuity gap in noise units
    iterations: int
    covariance: np.ndarray = field(repr=False)  # of the free coefficients
    status: str = "converged"
    rho: float = _PENALTY[-1]  # continuity weight of the last pass

    @property
    def continuous(self) -> bool:
        """Whether consecutive segments meet within ``CONTINUOUS`` noise levels: the
        fit is one trajectory of its system (False for a NaN gap)."""
        return bool(self.gap <= CONTINUOUS)

    @property
    def residual_variance(self) -> float:
        """Data misfit per degree of freedom, in noise variances (about 1 when the
        system is right and the noise level is estimated well)."""
        return self.data_cost / _dof(self.n_data, self.system, self.starts)

    def standard_errors(self) -> np.ndarray:
        """Standard errors of the free coefficients (covariance scaled by the residual
        variance), in the order of ``system.free_values()``."""
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0) * self.residual_variance)


class Problem:
    """The data, segments and weights of one refinement."""

    def __init__(self, system, times, observed, guesses, options=None):
        self.options = options = options or RefineOptions()
        self.system = system
        self.n_obs = system.n_observed
        self.times = [np.asarray(t, float) for t in times]
        self.observed = [np.asarray(x, float) for x in observed]
        stds = np.std(np.vstack(self.observed), axis=0)
        stds[stds == 0] = 1.0
        sigma, self.phi = with_ar1(measurement_noise(self.observed, self.times),
                                   self.observed, self.times)
        if options.noise is not None:
            sigma = np.asarray(options.noise, float)
        self.sigma = np.maximum(sigma, NOISE_FLOOR * stds)  # exact data: see NOISE_FLOOR
        relative = float(np.median(self.sigma / stds))
        guess_std = np.std(np.vstack(guesses), axis=0)
        guess_std[guess_std == 0] = 1.0
        # continuity residuals: every state in units of its own noise-like scale
        self.scale = np.concatenate([self.sigma, relative * guess_std[self.n_obs:]])
        # the median step over all samples: with two sampling rates the dense one, so
        # segments stay short in time (long ones converge more slowly and, from a
        # poor start, to the wrong minimum; measured on two-rate recordings)
        self.dt = dt = float(np.median(np.concatenate([np.diff(t) for t in self.times])))
        period = _dominant_period(self.observed, self.times)
        lo, hi = options.segment_samples
        duration = float(np.clip(period / 8, lo * dt, hi * dt))
        bound = 1e3 * max(1.0, float(np.max(np.abs(np.vstack(guesses)))))
        self.bound = bound
        self.integrator = Integrator(system, bound, device=options.device)
        self._integrators = {system.free.tobytes(): self.integrator}
        # a finite step budget: at most MAX_GRID steps per segment, however fast the
        # initial system's rates (a system that needs more is stiff or wild; if it blows
        # up on that grid, that is reported as BlowUp)
        step = float(np.clip(stable_step(self.integrator, guesses, system.coef),
                             duration / MAX_GRID, duration / 2))
        self.groups = make_groups(self.times, self.observed, duration, step, options.device)
        self.batches = make_batches(self.groups)  # a panel's recordings side by side
        self.carry = carry_over(self.groups, self.phi, dt)  # AR(1) noise: whitening
        self.n_segments = sum(g.n_segments for g in self.groups)
        starts = []
        for g in self.groups:
            t, gs = self.times[g.trajectory], np.asarray(guesses[g.trajectory])
            starts.append(np.column_stack([np.interp(g.starts, t, col) for col in gs.T]))
        self.initial_starts = np.vstack(starts)
        self.n_data = int(sum(int(g.mask.sum()) for g in self.groups)) * self.n_obs

    def for_system(self, system) -> Problem:
        """This problem (the same data, segments, grid and scales) for ``system``, whose
        features may differ from this one's."""
        other = copy.copy(self)
        other.system = system
        other.integrator = Integrator(system, self.bound, device=self.options.device)
        other._integrators = {system.free.tobytes(): other.integrator}
        return other

    def integrator_for(self, system) -> Integrator:
        """The integrator of ``system`` (same features, its own free coefficients)."""
        key = system.free.tobytes()
        if key not in self._integrators:
            self._integrators[key] = Integrator(system, self.bound, self.integrator.features,
                                                self.options.device)
        return self._integrators[key]

    def runs(self, system, starts, sensitivities=True, components=None, blow_ups=False,
             as_numpy=False):
        """``(group, segments, output)`` of :meth:`Integrator.run` for every group, in
        order, integrated batch by batch (:func:`.batches.run_groups`)."""
        return run_groups(self.integrator_for(system), system.coef, starts, self.groups,
                          self.batches, sensitivities, components, blow_ups, as_numpy)

    # ------------------------------------------------------------- residuals
    def equations(self, system, starts, weights, rho, jacobian=True):
        """Normal equations (or the cost only) at (system, starts); ``weights`` (n_seg,)
        multiply each segment's data residuals (0: held out), or (n_seg, samples) each
        sample's (the padded sample slots of :class:`.shooting.Group`). Numpy and
        compiled loops (:mod:`.data_rows`): the torch version's arithmetic to the bit."""
        n, n_free = starts.shape[1], system.n_free
        eq = NormalEquations(n_free, self.n_segments, n)
        data_cost = 0.0
        sig, scale = self.sigma, self.scale
        root = float(np.sqrt(rho))
        for g, segs, out in self.runs(system, starts, jacobian, self.n_obs, as_numpy=True):
            (vals, sens), (ends, sens_end) = out if jacobian else ((out[0], None),
                                                                    (out[1], None))
            mask = g.mask.numpy()
            w = sample_weights(weights[segs], mask)
            a = None if self.carry is None else self.carry[g.trajectory].numpy()
            gap = (starts[segs[1:]] - ends[:-1]) / scale * root
            if not jacobian:
                resid = whiten((vals - g.observed.numpy()) / sig * mask[..., None], a)
                data_cost += (squares := sum_of_squares(resid * w[..., None]))
                eq.cost += squares + sum_of_squares(gap)
                continue
            resid, jac = data_rows(vals, sens, g.observed.numpy(), mask, sig, w, a, n)
            data_cost += sum_of_squares(resid)
            eq.add(jac, resid.reshape(len(segs), -1), segs[:, None])
            if len(segs) > 1:
                se = sens_end[:-1] / scale[:, None] * root
                eye = np.broadcast_to(self._continuity_unit(root), (len(segs) - 1, n, n))
                jac_c = np.concatenate([-se[..., n:], -se[..., :n], eye], axis=-1)
                eq.add(jac_c, gap, np.stack([segs[:-1], segs[1:]], axis=1))
        eq.data_cost = data_cost
        return eq

    def _continuity_unit(self, root):
        """d gap / d next start (the identity over ``scale``, times ``root``), kept."""
        units = self.__dict__.setdefault("_units", {})
        if root not in units:
            units[root] = np.eye(len(self.scale)) / self.scale[:, None] * root
        return units[root]

    # ------------------------------------------------------------- fitting
    def fit(self, system=None, starts=None, weights=None, max_iterations=None,
            penalties=_PENALTY, give_up=np.inf, resolution=RESOLUTION, watch=None) -> Fit:
        """Levenberg-Marquardt with a continuity penalty raised until gaps are small.
        With ``give_up``, a fit whose misfit per degree of freedom (noise variances) is
        still above it after half its iterations, or after a pass, stops there: one
        that cannot compete costs no more. ``give_up`` may be a function that returns
        it, asked at every check (a bound that falls while the fit runs). ``watch`` (a
        :class:`GiveUpWatch`) records the checks, so that whether another bound would
        have stopped the fit sooner can be told afterwards. ``resolution``: see
        ``RESOLUTION``."""
        system = system or self.system
        starts = self.initial_starts if starts is None else starts
        weights = np.ones(self.n_segments) if weights is None else weights
        max_iterations = max_iterations or self.options.max_iterations
        values = system.free_values()
        total = 0
        dof = _dof(self.n_data, system, starts)
        bound = give_up if callable(give_up) else (lambda: give_up)
        watch = GiveUpWatch() if watch is None else watch
        watch.dof = dof
        for k, rho in enumerate(penalties):
            values, starts, eq, its, ok = levenberg_marquardt(
                self, system, values, starts, weights, rho, max_iterations,
                resolution=resolution, give_up=lambda: bound() * dof, watch=watch)
            total += its
            status = "converged" if ok else "iteration_limit"  # of the last pass
            if self._gap(system.with_free(values), starts) < _GAP:
                break
            if k + 1 < len(penalties):  # after the last pass nothing more is decided
                if watch.check(eq.data_cost, bound() * dof):
                    break
        fitted = system.with_free(values)
        return Fit(fitted, starts, eq.cost, eq.data_cost, self.n_data, self._gap(fitted, starts),
                   total, covariance(eq, system.n_free), status, rho)

    def _gap(self, system, starts):
        """Largest continuity gap between consecutive segments, in ``scale`` units."""
        worst = 0.0
        if all(g.n_segments < 2 for g in self.groups):
            return worst
        for g, segs, (_, ends) in self.runs(system, starts, False, components=0):
            if g.n_segments < 2:
                continue
            gap = (torch.as_tensor(starts[segs[1:]]) - ends[:-1]) / torch.as_tensor(self.scale)
            worst = max(worst, float(gap.abs().max()))
        return worst

    def jumps(self, fit: Fit) -> np.ndarray:
        """Largest jump of every hidden state at a segment boundary that the continuity
        penalty cannot see, relative to the state's own spread in that recording (std
        over its samples, at least 1% of its RMS). The penalty measures jumps in a unit
        set from the initial guess; a hidden state free to shrink (its loadings
        growing) below that unit can jump by its whole variation while the penalty
        reads a small gap: a trajectory that does not join, which no solution of the
        system has. Where the spread is at least the unit the penalty sees the jumps
        (and the fit reports its gap), so they count as 0 here."""
        n_obs = self.n_obs
        worst = np.zeros(fit.starts.shape[1] - n_obs)
        unit = self.scale[n_obs:]
        if all(g.n_segments < 2 for g in self.groups):
            return worst
        for g, segs, (vals, ends) in self.runs(fit.system, fit.starts, False):
            if g.n_segments < 2:
                continue
            hidden = vals.numpy()[g.mask.numpy()][:, n_obs:]
            rms = np.sqrt(np.mean(hidden**2, axis=0))
            spread = np.maximum(np.std(hidden, axis=0), 1e-2 * rms)
            jump = np.abs(fit.starts[segs[1:], n_obs:] - ends[:-1, n_obs:].numpy()).max(axis=0)
            ratio = np.where(spread < unit, jump / (spread + 1e-300), 0.0)
            worst = np.maximum(worst, np.where(np.isfinite(ratio), ratio, np.inf))
        return worst

    def joins(self, fit: Fit) -> bool:
        """Whether no hidden state jumps at a segment boundary by more than ``JOIN`` of
        its spread where the continuity penalty cannot see it (:meth:`jumps`): the fit
        is a trajectory of its system."""
        return bool(np.all(self.jumps(fit) <= JOIN))

    def trajectories(self, fit: Fit):
        """The fitted states at every sample, one (T, n_states) array per trajectory."""
        return self.trajectories_of((fit.system, fit.starts))

    def trajectories_of(self, pair):
        """States at every sample of ``(system, starts)`` (NaN where it blows up)."""
        system, starts = pair
        out = [np.full((len(t), starts.shape[1]), np.nan) for t in self.times]
        for g, _, run in self.runs(system, starts, False, blow_ups=True):
            if run is None:  # this recording blows up
                continue
            vals = run[0]
            rows = g.sample_index[g.mask.numpy()]
            out[g.trajectory][rows] = vals.numpy()[g.mask.numpy()]
        return out

    def state_std(self, fit: Fit, max_size: int = 2000):
        """Standard deviation of every state at every sample (delta method: the
        sensitivities of the states to the free coefficients and the segment's start,
        and their covariance); NaN when the problem is too large to invert densely."""
        out = [np.full((len(t), fit.starts.shape[1]), np.nan) for t in self.times]
        eq = self.equations(fit.system, fit.starts, np.ones(self.n_segments), fit.rho)
        if eq.size > max_size:
            return out
        try:
            cov = np.linalg.inv(as_array(eq.matrix())) * fit.residual_variance
        except np.linalg.LinAlgError:
            return out
        n, p = fit.starts.shape[1], fit.system.n_free
        for g, segs, ((_, sens), _) in self.runs(fit.system, fit.starts):
            sens = torch.cat([sens[..., n:], sens[..., :n]], dim=-1).numpy()  # (coef, start)
            mask = g.mask.numpy()
            for k, seg in enumerate(segs):
                idx = np.concatenate([np.arange(p), p + seg * n + np.arange(n)])
                block = cov[np.ix_(idx, idx)]
                var = np.einsum("mic,cd,mid->mi", sens[k], block, sens[k])
                rows = g.sample_index[k][mask[k]]
                out[g.trajectory][rows] = np.sqrt(np.maximum(var[mask[k]], 0.0))
        return out

    def segment_errors(self, fit: Fit, which):
        """Mean squared data residual (noise units) of each segment in ``which``."""
        errors = []
        for g, segs, resid in self._squared_residuals(fit):
            per = resid.sum(dim=(1, 2)) / (g.mask.sum(dim=1) * self.n_obs).clamp_min(1)
            errors += [float(per[k]) for k, s in enumerate(segs) if which[s]]
        return np.array(errors)

    def sample_errors(self, fit: Fit, which):
        """Squared data residual (noise units, averaged over the observed states) of
        every sample marked in ``which`` (n_seg, samples), group by group."""
        errors = []
        for g, segs, resid in self._squared_residuals(fit):
            held = np.asarray(which[segs][:, :g.mask.shape[1]], bool) & g.mask.numpy()
            errors.append(resid.mean(dim=2).numpy()[held])
        return np.concatenate(errors)

    def recording_errors(self, fit: Fit, which):
        """Misfit per degree of freedom (noise variances) of every recording whose
        segments are all in ``which``: squared data residuals over samples times
        observed states less the recording's initial values (one per state)."""
        n_states = fit.starts.shape[1]
        return np.array([float(resid.sum()) / max(int(g.mask.sum()) * self.n_obs - n_states, 1)
                         for g, segs, resid in self._squared_residuals(fit)
                         if all(which[segs])])

    def _squared_residuals(self, fit: Fit):
        """``(group, its segments, squared whitened data residuals)`` for every group:
        observed states in noise units, padding zero."""
        sig = torch.as_tensor(self.sigma)
        for g, segs, (vals, _) in self.runs(fit.system, fit.starts, False, self.n_obs):
            a = None if self.carry is None else self.carry[g.trajectory]
            yield g, segs, whiten((vals - g.observed) / sig * g.mask[..., None], a) ** 2


def _dominant_period(observed, times):
    """The longest crossing period over the states and trajectories
    (:func:`latentsindy._core.oscillation.crossing_periods`); the first trajectory's
    span when nothing oscillates."""
    best = max((p for x, t in zip(observed, times, strict=True)
                for p in crossing_periods(x, t)), default=0.0)
    return best if best > 0 else float(times[0][-1] - times[0][0])


