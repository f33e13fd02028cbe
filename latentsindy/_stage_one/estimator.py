"""`DynamicSINDy`: stage one as a scikit-learn-style estimator."""

from __future__ import annotations

import contextlib
import copy

import numpy as np
import torch
from scipy.optimize import nnls

from .._core import saving
from .._core import validation as val
from .._core.derivatives import noise_level, state_noise
from .._core.differentiation import differentiate
from .._core.library import check_library, fit_library
from .._core.local_fits import positions as time_positions
from .._core.reprs import estimator_repr
from .._core.timing import timed
from ..generators import build_generator, generator_class
from .assessment import assess
from .coefficient_model import CoefficientModel, least_squares_constants
from .coefficients import CoefficientSeries
from .decisions import adopt_structure
from .evidence import VaryingCoefficients
from .sequential import (
    SequentialCoefficientModel,
    SequentialTrainingOptions,
    train_sequential,
    windowed_constants,
)
from .training import TrainingOptions, make_training_options, train


class DynamicSINDy:
    """Time-varying SINDy coefficients from a deep generative model (dynamic SINDy).

    Learns Xi(t) such that ``Theta(x(t)) Xi(t) ~ xdot(t)`` for any pysindy feature
    library, in two phases: a sparsity phase that prunes terms, then a refit on the
    fixed support with stronger smoothing. Between the two, pruned terms that the data
    still need (least-squares checks on the residual, and on the varying coefficients
    for terms they absorbed) are restored as constants.
    Coefficients are reported in physical units.

    Parameters
    ----------
    library : pysindy feature library, optional
        Candidate functions Theta (default ``PolynomialLibrary(degree=2)``).
    generator : {"timevae", "hypersindy"}
        The deep generative model mapping the series to coefficient series:
        ``"timevae"`` reads the whole series at once (best up to a few thousand
        samples); ``"hypersindy"`` (dynamic HyperSINDy) reads it window by window,
        with memory independent of the series length.
    generator_options : dict, optional
        Architecture options of the generator (e.g. ``{"latent_dim": 8}``). What they
        leave to the data is chosen from it (timeVAE's ``n_knots``: what the
        differentiator resolves); the options used are ``generator_options_``.
    training : TrainingOptions, SequentialTrainingOptions or dict, optional
        Loss weights, steps and pruning threshold: :class:`TrainingOptions` for
        ``"timevae"``, :class:`SequentialTrainingOptions` for ``"hypersindy"``.
    differentiation_method : pysindy differentiation object, optional
        Used when ``x_dot`` is not given (default: a noise-adaptive Savitzky-Golay).
    structure : {"evidence", "generator"}
        Who decides which terms exist and which vary. ``"evidence"`` (default): after
        the generator's support phase, an exact Bayesian varying-coefficient model on
        the integral form of the data scores the structures near the generator's and
        the best one is refitted, its constants pinned at the exact model's values
        (a generator's variation can stand in for a missing term; the exact model's
        evidence cannot be fooled that way). ``"generator"``: the generator's own
        pruning and variation (the seed paper's method).
    support : dict or bool array, optional
        Fixed structure, e.g. ``{"x": ["y"]}`` (``xdot = c(t) y``); equations not
        named are found by sparsity. A bool array of shape (n_states, n_features)
        fixes every equation.
    time_varying : dict or bool array, optional
        Terms allowed to vary in time (default: all). Others are fitted as constants.
        E.g. ``{"y": ["1"]}``: only the constant term of ydot varies.
    device : str
        Torch device ("cpu" or "cuda").
    verbose : bool
        Show a progress bar during training.
    seed : int
        Seeds all randomness; CPU runs with the same seed are repeatable.

    Attributes
    ----------
    support_, time_varying_ : ndarray of bool, shape (n_states, n_features)
        Terms kept, and those of them that vary in time.
    generator_options_ : frozen options dataclass
        The generator's options as built, with what was left to the data filled in.
    restored_terms_ : list of (state, feature)
        Terms pruned in the sparsity phase and restored by the least-squares check.
    history_ : list of dict
        Loss terms at every optimiser step.

    Examples
    --------
    >>> import pysindy as ps
    >>> from latentsindy import DynamicSINDy, systems
    >>> data = systems.harmonic_oscillator(A=-2.0, B=1.0, n_times=300)
    >>> model = DynamicSINDy(ps.PolynomialLibrary(degree=1, include_bias=False),
    ...                      training={"support_steps": 50, "refit_steps": 50}, verbose=False)
    >>> model = model.fit(data.x, data.t, feature_names=["x", "y"])
    >>> model.coefficients(n_samples=4).mean.shape
    (300, 2, 2)
    """

    def __init__(self, library=None, *, generator="timevae", generator_options=None,
                 training=None, differentiation_method=None, structure="evidence",
                 support=None, time_varying=None, device="cpu", verbose=True, seed=0):
        self.library = library
        self.generator = generator
        self.generator_options = generator_options
        self.training = training
        self.differentiation_method = differentiation_method
        self.structure = structure
        self.support = support
        self.time_varying = time_varying
        self.device = device
        self.verbose = verbose
        self.seed = seed

    # ------------------------------------------------------------------ fit
    def fit(self, x, t, *, x_dot=None, feature_names=None) -> DynamicSINDy:
        """Fit time-varying coefficients to one or several trajectories.

        Parameters
        ----------
        x : array (n_times, n_states) or list of such arrays
            Several trajectories must share the same time-varying dynamics and times.
        t : float, array (n_times,), or list of arrays
            Sample spacing or sample times.
        x_dot : array or list of arrays, optional
            Known derivatives; estimated with ``differentiation_method`` otherwise.
        feature_names : list of str, optional
            State names (default ``x0, x1, ...``).

        Returns
        -------
        self
        """
        sequential = generator_class(self.generator).sequential
        options = make_training_options(
            self.training, SequentialTrainingOptions if sequential else TrainingOptions,
            self.generator)
        trajs = val.as_trajectories(x, "x")
        times = val.as_times(t, trajs)
        _check_shared_times(times)
        names = val.check_feature_names(feature_names, trajs[0].shape[1])
        device = val.check_device(self.device)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int | np.integer):
            raise TypeError(f"seed must be a non-negative int; got {self.seed!r}.")
        if self.seed < 0:
            raise ValueError(f"seed must be a non-negative int; got {self.seed}.")
        if self.structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {STRUCTURES}; got {self.structure!r}.")
        if x_dot is None:
            method = copy.deepcopy(self.differentiation_method)  # never mutate the user's
            xdots, noise_std, weights = differentiate(method, trajs, times)
        else:
            xdots = val.as_trajectories(x_dot, "x_dot")
            if [d.shape for d in xdots] != [tr.shape for tr in trajs]:
                raise ValueError(f"x_dot shapes {[d.shape for d in xdots]} must match x shapes "
                                 f"{[tr.shape for tr in trajs]}.")
            noise_std = noise_level(list(xdots), list(times))
            weights = [np.ones_like(d) for d in xdots]
        library = check_library(self.library)
        thetas, feature_list = fit_library(library, trajs, names)
        support = val.term_mask(self.support, names, feature_list, "support", default=True,
                             unnamed=True)
        free_rows = val.free_rows(self.support, names)
        varying = val.term_mask(self.time_varying, names, feature_list, "time_varying",
                             default=True, unnamed=False)

        theta = np.stack(thetas)  # (B, T, F)
        xdot = np.stack(xdots)  # (B, T, n)
        self.feature_scale_ = np.sqrt(np.mean(theta**2, axis=(0, 1)))
        self.feature_scale_[self.feature_scale_ == 0] = 1.0
        self.derivative_scale_ = np.sqrt(np.mean(xdot**2, axis=(0, 1)))
        self.derivative_scale_[self.derivative_scale_ == 0] = 1.0
        # variance of the derivative noise in normalised units (floored: no data are exact)
        self.noise_variance_ = max(float(np.mean((noise_std / self.derivative_scale_) ** 2)),
                                   1e-8)
        dev = torch.device(device)
        as_t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32,  # noqa: E731
                                         device=dev)
        theta_n = as_t(theta / self.feature_scale_)
        xdot_n = as_t(xdot / self.derivative_scale_)
        weights_t = as_t(np.stack(weights))
        inputs = as_t(_encoder_inputs(np.stack(trajs), xdot).transpose(0, 2, 1))
        exact = VaryingCoefficients(trajs, times, [th / self.feature_scale_ for th in thetas],
                                    self.derivative_scale_, *state_noise(trajs, times))
        choices = []

        def decide(model):  # between the generator's phases
            choices.append(exact.choose(model.support.cpu().numpy(),
                                        model.time_varying.cpu().numpy() > 0, free_rows,
                                        varying, options.threshold))
            adopt_structure(model, choices[-1])

        with _seeded(self.seed, dev):  # repeatable, and the caller's RNG state is untouched
            # the exact model's knots are one every half differentiator window (cubic
            # splines: three more knots than intervals): what the data resolve
            gen = build_generator(self.generator, inputs.shape[1], support.size,
                                  self.generator_options, intervals=exact.n_knots - 3)
            support_t = torch.as_tensor(support, device=dev)
            gen.allocate(theta.shape[1], sample_positions(times[0], dev))
            if sequential:
                constants = windowed_constants(theta_n, xdot_n, support_t, options.window)
                model_cls, fit_fn = SequentialCoefficientModel, train_sequential
            else:
                constants = least_squares_constants(theta_n, xdot_n, support_t)
                model_cls, fit_fn = CoefficientModel, train
            model = model_cls(gen, constants, support_t,
                              torch.as_tensor(varying, dtype=torch.float32)).to(dev)
            self.history_ = fit_fn(model, theta_n, xdot_n, weights_t, inputs,
                                   self.noise_variance_, torch.as_tensor(free_rows, device=dev),
                                   options, self.verbose,
                                   decide if self.structure == "evidence" else None)
        model.eval()
        self.encoder_inputs_ = inputs
        self.library_ = library
        self.state_names_ = tuple(names)
        self.feature_names_ = tuple(feature_list)
        self.times_ = times[0]
        self.x_ = trajs
        self.x_dot_ = xdots
        self.support_ = model.support.cpu().numpy().copy()
        self.time_varying_ = model.time_varying.cpu().numpy().astype(bool) & self.support_
        self.n_parameters_ = sum(p.numel() for p in gen.parameters())
        self.generator_options_ = gen.options
        self.restored_terms_ = [(names[i], feature_list[j]) for i, j in model.restored]
        with torch.no_grad():
            mean_n = model(inputs, 0)[0][0].cpu().double().numpy()
        if not choices:  # the generator decided: ask the exact model anyway (doubts)
            choices.append(exact.choose(self.support_, self.time_varying_, free_rows,
                                        varying, options.threshold))
        scale = self.derivative_scale_[:, None] / self.feature_scale_[None, :]
        self.assessment_ = assess(exact, self.support_, self.time_varying_, choices[-1],
                                  mean_n * scale, options.threshold, names, feature_list,
                                  scale, _misfit(theta / self.feature_scale_, xdot,
                                                 np.stack(weights), mean_n, noise_std,
                                                 self.derivative_scale_))
        self.doubts_ = self.assessment_.doubts
        self.model_ = model  # last: a fit that fails midway leaves the estimator unfitted
        return self

    def get_params(self, deep=True):
        """Constructor parameters (scikit-learn convention)."""
        return {k: getattr(self, k) for k in _PARAMS}

    def __repr__(self) -> str:
        return estimator_repr(self, self.get_params())

    def set_params(self, **params):
        """Set constructor parameters; unknown names are an error."""
        unknown = sorted(set(params) - set(_PARAMS))
        if unknown:
            raise ValueError(f"Unknown parameter(s) {unknown}; valid ones are {list(_PARAMS)}.")
        for k, v in params.items():
            setattr(self, k, v)
        return self

    # ------------------------------------------------------------ results
    @timed("stage one: posterior samples")
    def coefficients(self, n_samples: int = 64) -> CoefficientSeries:
        """Posterior mean, spread and samples of Xi(t) in physical units."""
        self._check_fitted()
        n_samples = val.check_positive(n_samples, "n_samples", integer=True)
        with torch.no_grad(), _seeded(self.seed + 1, self.encoder_inputs_.device):
            samples, _ = self.model_(self.encoder_inputs_, int(n_samples))
            mean, _ = self.model_(self.encoder_inputs_, 0)
        scale = self.derivative_scale_[:, None] / self.feature_scale_[None, :]
        samples = samples.cpu().double().numpy()  # a new array: scaled in place
        samples *= scale
        mean = mean[0].cpu().double().numpy() * scale
        std = samples.std(axis=0) if samples.shape[0] > 1 else np.zeros_like(mean)
        lower, upper, doubts = None, None, ()
        exact = getattr(self, "assessment_", None)
        if exact is not None:  # the band: the exact model's, widened to hold ours
            lower = np.minimum(exact.lower, mean - 2.0 * std) * self.support_
            upper = np.maximum(exact.upper, mean + 2.0 * std) * self.support_
            doubts = exact.doubts
        return CoefficientSeries._of(self.times_, mean, samples, self.state_names_,
                                     self.feature_names_, self.support_, self.time_varying_,
                                     lower, upper, doubts, std=std, own=True)

    def predict(self, coefficients: CoefficientSeries | None = None) -> list[np.ndarray]:
        """Derivatives Theta(x) Xi(t) on the training trajectories, one array each."""
        self._check_fitted()
        if self.library_ is None:
            raise RuntimeError("This DynamicSINDy was loaded from a file without its feature "
                               "library (only polynomial and Fourier libraries are stored); "
                               "predict() needs it: refit, or compute Theta(x) yourself.")
        coefficients = coefficients or self.coefficients(n_samples=1)
        thetas = [np.asarray(a) for a in self.library_.transform(self.x_)]
        return [np.einsum("tf,tnf->tn", th, coefficients.mean) for th in thetas]

    def save(self, path) -> None:
        """Write the fitted model to ``path`` (``.npz``); read it with
        :func:`latentsindy.load`, which gives the same ``coefficients()``."""
        saving.save(self, path)

    def coefficient_noise(self, coefficients: CoefficientSeries | None = None) -> np.ndarray:
        """Standard deviation of white noise carried by each coefficient, from residuals.

        If coefficient k of equation i is its smooth posterior mean plus white noise of
        standard deviation s_ik, the residual ``r_i = xdot_i - Theta Xi_mean`` has
        variance ``sigma_i^2 + sum_k s_ik^2 Theta_k^2`` at every time: a regression of
        ``r_i^2`` on ``1`` and ``Theta_k^2`` (non-negative least squares, the kept
        terms) estimates every s_ik (method of moments). The posterior spread
        (:attr:`CoefficientSeries.std`) is a different thing, the uncertainty of the
        smooth mean. Noise in the coefficients is only visible in derivatives that
        carry it: pass exact ``x_dot`` to ``fit``; derivatives estimated from a smoothed
        x average it away.

        Returns
        -------
        ndarray (n_states, n_features)
            0 outside the support; NaN for a constant feature (such as ``"1"``), whose
            noise cannot be told apart from the derivative noise.
        """
        self._check_fitted()
        fitted = self.predict(coefficients)
        thetas = [np.asarray(a) for a in self.library_.transform(self.x_)]
        theta = np.concatenate(thetas)
        resid = np.concatenate([d - p for d, p in zip(self.x_dot_, fitted, strict=True)])
        out = np.zeros(self.support_.shape)
        constant = np.ptp(theta**2, axis=0) <= 1e-12 * (np.abs(theta**2).max(axis=0) + 1e-300)
        for i in range(resid.shape[1]):
            out[i, self.support_[i] & constant] = np.nan
            cols = np.flatnonzero(self.support_[i] & ~constant)
            design = np.column_stack([np.ones(theta.shape[0]), theta[:, cols] ** 2])
            scale = np.sqrt(np.mean(design**2, axis=0))
            scale[scale == 0] = 1.0
            variances, _ = nnls(design / scale, resid[:, i] ** 2)
            out[i, cols] = np.sqrt(variances[1:] / scale[1:])
        return out

    def _check_fitted(self):
        if not hasattr(self, "model_"):
            raise RuntimeError("This DynamicSINDy is not fitted yet; call fit(x, t) first.")


_PARAMS = ("library", "generator", "generator_options", "training", "differentiation_method",
           "structure", "support", "time_varying", "device", "verbose", "seed")
STRUCTURES = ("evidence", "generator")


@contextlib.contextmanager
def _seeded(seed, device):
    """Seed torch inside the block and restore the caller's RNG state afterwards."""
    devices = [device] if torch.device(device).type == "cuda" else []
    with torch.random.fork_rng(devices=devices):
        torch.manual_seed(seed)
        yield


def sample_positions(times, device):
    """The generators' time axis: sample times in mean steps (float32 tensor), or None
    on a uniform grid."""
    pos = time_positions(times)
    return None if pos is None else torch.as_tensor(pos, dtype=torch.float32, device=device)


def _misfit(theta, xdot, weights, mean_n, noise_std, derivative_scale):
    """Each equation's weighted mean squared derivative misfit (normalised) over its
    derivative noise variance."""
    pred = np.einsum("btf,tnf->btn", theta, mean_n)
    resid = xdot / derivative_scale - pred
    noise = np.maximum((np.asarray(noise_std) / derivative_scale) ** 2, 1e-12)
    return np.mean(weights * resid**2, axis=(0, 1)) / noise


def _encoder_inputs(x, xdot):
    """Standardised states and derivatives as encoder channels: (B, T, 2n)."""
    xs = (x - x.mean(axis=(0, 1))) / np.maximum(x.std(axis=(0, 1)), 1e-12)
    ds = xdot / np.maximum(np.sqrt(np.mean(xdot**2, axis=(0, 1))), 1e-12)
    return np.concatenate([xs, ds], axis=-1)


def _check_shared_times(times):
    first = times[0]
    for k, ti in enumerate(times[1:], start=1):
        if ti.shape != first.shape or not np.allclose(ti - ti[0], first - first[0],
                                                      rtol=1e-6, atol=1e-9):
            raise ValueError(
                "Trajectories must share the same time-varying dynamics on the same time "
                f"grid; trajectory {k} has {ti.shape[0]} times vs {first.shape[0]} (or other "
                "spacing). Resample them onto one grid."
            )
