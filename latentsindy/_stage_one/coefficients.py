"""Frozen result objects of stage one."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy.ndimage import uniform_filter1d

from .._core.doubt import as_doubts
from .figures import plot_coefficients


@dataclass(frozen=True, repr=False)
class CoefficientSeries:
    """Time-varying SINDy coefficients with uncertainty, in physical units.

    Attributes
    ----------
    times : ndarray, shape (n_times,)
    mean : ndarray, shape (n_times, n_states, n_features)
        Posterior-mean coefficients; ``mean[k]`` has the layout of pysindy's
        ``SINDy.coefficients()`` at time ``times[k]``.
    std : ndarray, shape (n_times, n_states, n_features)
        Standard deviation across posterior samples.
    samples : ndarray, shape (n_samples, n_times, n_states, n_features)
    state_names, feature_names : tuple of str
    support : ndarray of bool, shape (n_states, n_features)
        Terms kept by the sparsity stage.
    time_varying : ndarray of bool, shape (n_states, n_features)
        Terms allowed to vary in time (the others are constants).
    noise_across_samples : ndarray, shape (n_states, n_features)
        The paper's first noise estimate: std across samples, averaged over time.
    noise_around_smooth_mean : ndarray, shape (n_states, n_features)
        The paper's second estimate: std over time of each sample around its own
        smoothed version, averaged over samples.
    lower, upper : ndarray, shape (n_times, n_states, n_features)
        The uncertainty band. From :class:`DynamicSINDy`: the 95% interval of an
        exact Bayesian varying-coefficient model of the data (integral form,
        adaptive smoothness, noise level from the data) on the fitted structure,
        joined with those of every structure that explains the data as well, and
        widened to hold the generator's mean +- 2 posterior std. It covers noise,
        smoothing bias at transitions (the exact model smooths adaptively and its
        posterior spreads there) and doubt about the structure; it does not cover a
        wrong library or a derivative-free misfit the library cannot express (see
        ``doubts``), nor white noise carried by the coefficients themselves
        (:meth:`DynamicSINDy.coefficient_noise`). Elsewhere (baselines, files
        without it): mean +- 2 ``std``.
    doubts : tuple of Doubt
        Checks the fit failed, each a kind and a sentence (empty: none).
    """

    times: np.ndarray
    mean: np.ndarray
    std: np.ndarray
    samples: np.ndarray
    state_names: tuple[str, ...]
    feature_names: tuple[str, ...]
    support: np.ndarray
    time_varying: np.ndarray
    noise_across_samples: np.ndarray
    noise_around_smooth_mean: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    doubts: tuple[str, ...] = ()

    def __post_init__(self):
        object.__setattr__(self, "doubts", as_doubts(self.doubts))

    def __repr__(self) -> str:
        varying = [f"{f} in d{s}/dt" for s, f in self.varying_terms()]
        doubts = f", {len(self.doubts)} doubt{'s' if len(self.doubts) > 1 else ''}" \
            if self.doubts else ""
        n = len(self.active_terms())
        return (f"CoefficientSeries({len(self.times)} times, {n} term{'s' if n != 1 else ''}, "
                f"varying: {', '.join(varying) or 'none'}{doubts})")

    def __str__(self) -> str:
        return self.summary()

    def varying_terms(self) -> list[tuple[str, str]]:
        """(state, feature) of every term allowed to vary in time."""
        return [(self.state_names[i], self.feature_names[j])
                for i, j in zip(*np.nonzero(self.time_varying & self.support), strict=True)]

    @classmethod
    def from_samples(cls, times, mean, samples, state_names, feature_names, support,
                     time_varying, *, lower=None, upper=None,
                     doubts=()) -> CoefficientSeries:
        return cls._of(times, mean, samples, state_names, feature_names, support,
                       time_varying, lower, upper, doubts)

    @classmethod
    def _of(cls, times, mean, samples, state_names, feature_names, support, time_varying,
            lower, upper, doubts, std=None, own=False) -> CoefficientSeries:
        """:meth:`from_samples`; ``std``: the samples' standard deviation, if made
        already; ``own``: ``samples`` and ``std`` are the caller's to give away, frozen
        in place rather than copied (64 samples of 20,000 times of 10 terms are 100 MB)."""
        if std is None:
            std = samples.std(axis=0) if samples.shape[0] > 1 else np.zeros_like(mean)
        width = max(5, (len(times) // 50) | 1)
        smooth = uniform_filter1d(samples, size=width, axis=1, mode="nearest")
        around = _spread_around(samples, smooth).mean(axis=0)
        lower = mean - 2.0 * std if lower is None else lower
        upper = mean + 2.0 * std if upper is None else upper
        if not own:
            std, samples = np.array(std, copy=True), np.array(samples, copy=True)
        t, m, sup, tv, n1, n2, lo, hi = (np.array(a, copy=True) for a in (
            times, mean, support, time_varying, std.mean(axis=0), around, lower, upper))
        for a in (t, m, std, samples, sup, tv, n1, n2, lo, hi):
            a.setflags(write=False)
        return cls(t, m, std, samples, tuple(state_names), tuple(feature_names), sup, tv,
                   n1, n2, lo, hi, as_doubts(doubts))

    @property
    def half_width(self) -> np.ndarray:
        """Half the band's width, (n_times, n_states, n_features)."""
        return 0.5 * (self.upper - self.lower)

    def term(self, state: str, feature: str) -> np.ndarray:
        """Mean series of one coefficient, e.g. ``term("x", "y")``."""
        return self.mean[:, self._state(state), self._feature(feature)]

    def term_std(self, state: str, feature: str) -> np.ndarray:
        """Posterior std of one coefficient over time (the generator's spread)."""
        return self.std[:, self._state(state), self._feature(feature)]

    def term_band(self, state: str, feature: str) -> tuple[np.ndarray, np.ndarray]:
        """(lower, upper) of one coefficient's band over time."""
        i, j = self._state(state), self._feature(feature)
        return self.lower[:, i, j], self.upper[:, i, j]

    def _state(self, name):
        if name not in self.state_names:
            raise KeyError(f"Unknown state {name!r}; states are {list(self.state_names)}.")
        return self.state_names.index(name)

    def _feature(self, name):
        if name not in self.feature_names:
            raise KeyError(f"Unknown feature {name!r}; features are {list(self.feature_names)}.")
        return self.feature_names.index(name)

    def active_terms(self) -> list[tuple[str, str]]:
        """(state, feature) pairs in the support."""
        rows, cols = np.nonzero(self.support)
        return [(self.state_names[i], self.feature_names[j]) for i, j in zip(rows, cols,
                                                                              strict=True)]

    def switch_times(self, min_jump: float = 0.2, window: int | None = None,
                     terms=None) -> np.ndarray:
        """Times at which the coefficients switch, read off the coefficient track.

        At every time the mean of each varying coefficient over the ``window`` samples
        after it is compared with the mean over the ``window`` samples before it,
        relative to the coefficient's typical size (its mean absolute value). Each
        stretch of time where the largest such change over all terms reaches
        ``min_jump`` is one switch, placed where the change peaks. A smooth transition
        gives one switch at its middle; a coefficient that varies continuously gives
        one at each steep part.

        Parameters
        ----------
        min_jump : float
            Smallest relative change of a coefficient that counts as a switch.
        window : int, optional
            Samples on each side (default: 1/20 of the series, at least 2).
        terms : list of (state, feature), optional
            Coefficients to read (default: every varying one). A small coefficient's
            wiggles are large relative to its own size: name the terms of interest.

        Examples
        --------
        >>> import numpy as np
        >>> t = np.linspace(0, 10, 1000)
        >>> a = np.where(t < 4, -1.0, -3.0)[:, None, None]
        >>> c = CoefficientSeries.from_samples(t, a, a[None], ["x"], ["y"],
        ...                                    np.ones((1, 1), bool), np.ones((1, 1), bool))
        >>> c.switch_times().round(2).tolist()
        [4.0]
        """
        n_times = len(self.times)
        window = max(2, n_times // 20) if window is None else int(window)
        if window < 1 or 2 * window > n_times:
            raise ValueError(f"window must be between 1 and half the series ({n_times // 2}); "
                             f"got {window}.")
        if terms is None:
            rows, cols = np.nonzero(self.support & self.time_varying)
        else:
            rows = np.array([self._state(a) for a, _ in terms], dtype=int)
            cols = np.array([self._feature(b) for _, b in terms], dtype=int)
        if len(rows) == 0:
            return np.array([])
        x = self.mean[:, rows, cols]
        x = x / np.maximum(np.abs(x).mean(axis=0), 1e-300)
        csum = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(x, axis=0)])
        k = np.arange(window, n_times - window + 1)
        before = (csum[k] - csum[k - window]) / window
        after = (csum[k + window] - csum[k]) / window
        change = np.abs(after - before).max(axis=1)
        # every contiguous stretch where the change reaches min_jump is one switch,
        # placed where the change peaks
        above = np.concatenate([[False], change >= min_jump, [False]])
        edges = np.flatnonzero(np.diff(above.astype(int)))
        found = [int(k[a + np.argmax(change[a:b])]) for a, b in zip(edges[::2], edges[1::2],
                                                                     strict=True)]
        return self.times[found] if found else np.array([])

    def plot(self, truth=None, *, terms=None, path=None, figsize=None):
        """Coefficients over time with +- 2 std bands, switch times marked.

        Needs matplotlib (``pip install "latentsindy[plot]"``).

        Parameters
        ----------
        truth : dict {(state, feature): array over ``times``}, optional
            Known coefficients, drawn dashed.
        terms : list of (state, feature), optional
            Coefficients to draw (default: every active one).
        path : str or Path, optional
            Also save the figure there.

        Returns
        -------
        matplotlib.figure.Figure
        """
        return plot_coefficients(self, truth, terms=terms, figsize=figsize, path=path)

    def summary(self) -> str:
        lines = [f"Time-varying SINDy coefficients: {len(self.times)} times, "
                 f"{self.samples.shape[0]} samples"]
        for i, s in enumerate(self.state_names):
            parts = []
            for j, f in enumerate(self.feature_names):
                if not self.support[i, j]:
                    continue
                m = self.mean[:, i, j]
                kind = "varies" if self.time_varying[i, j] else "constant"
                parts.append(f"{f}: mean {m.mean():.4g}, range [{m.min():.4g}, {m.max():.4g}] "
                             f"({kind})")
            lines.append(f"  d{s}/dt: " + ("; ".join(parts) if parts else "0"))
        if self.doubts:
            lines.append("  DOUBTS:")
            lines += [f"    - {d}" for d in self.doubts]
        return "\n".join(lines)


def _spread_around(samples, smooth):
    """``(samples - smooth).std(axis=1)``, numpy's numbers without its temporaries.
    Where the difference is laid out in C order with more than one term, numpy sums
    along time one time after the other (the terms are its inner loop), as the kernel
    does; otherwise (one term, or a difference with time innermost, which the
    estimator's C-order smoothed copy never gives) it sums pairwise, and numpy is used
    (64 samples of 20,000 times of 9 terms: 0.17 -> 0.05 s)."""
    diff = samples - smooth
    n_samples, n_times = diff.shape[:2]
    if (diff.dtype != np.float64 or not diff.flags.c_contiguous or n_times < 1
            or int(np.prod(diff.shape[2:])) < 2):
        return diff.std(axis=1)
    flat = diff.reshape(n_samples, n_times, -1)
    return _std_along_time(flat).reshape((n_samples, *diff.shape[2:]))


@njit(cache=True, nogil=True)
def _std_along_time(a):
    """The standard deviation over axis 1 of ``a`` (S, T, R): mean, then the mean
    square about it, each summed in time order."""
    n_samples, n_times, terms = a.shape
    out = np.empty((n_samples, terms))
    for s in range(n_samples):
        total = np.zeros(terms)
        for t in range(n_times):
            for r in range(terms):
                total[r] += a[s, t, r]
        mean = total / n_times
        square = np.zeros(terms)
        for t in range(n_times):
            for r in range(terms):
                d = a[s, t, r] - mean[r]
                square[r] += d * d
        for r in range(terms):
            out[s, r] = np.sqrt(square[r] / n_times)
    return out
