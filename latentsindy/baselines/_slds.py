"""SLDS and rSLDS as switch finders, through Linderman's ``ssm`` (the paper's baseline).

The paper's recipe (supplement 4.1): choose the number of discrete states K (2 for one
switch), project the data on principal components, initialise the discrete states with
an autoregressive HMM, then fit the SLDS (Markov switches) or the rSLDS (switches that
also depend on the continuous state through a logistic regression) by Laplace-EM; the
most likely discrete sequence segments the series. ``ssm``'s own ``initialize`` does the
PCA and the AR-HMM. Optionally time enters as an input, as the paper tried.

``ssm`` is an optional extra. PyPI has only ``ssm==0.0.1``, which needs a build step::

    pip install numpy cython wheel setuptools
    pip install --no-build-isolation ssm==0.0.1
    pip install -e ".[baselines]"

and whose import refers to ``autograd.scipy.misc.logsumexp``, which autograd moved to
``autograd.scipy.special``; :func:`import_ssm` maps the old name before importing.
"""

from __future__ import annotations

import contextlib
import io
import sys
import types
import warnings
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linear_sum_assignment

from .._core import validation as val
from ._inputs import one_trajectory

METHODS = {"arhmm": None, "slds": "standard", "rslds": "recurrent"}
INSTALL = ('pip install numpy cython wheel setuptools && pip install --no-build-isolation '
           'ssm==0.0.1 && pip install -e ".[baselines]"')


def import_ssm():
    """Import ``ssm``, mapping ``autograd.scipy.misc`` for its old import; an ImportError
    that says how to install it when it is missing."""
    try:
        import autograd.scipy as ascipy
        import autograd.scipy.special as special
    except ImportError:
        raise ImportError(f"The SLDS baselines need ssm and autograd: {INSTALL}") from None
    if "autograd.scipy.misc" not in sys.modules:
        shim = types.ModuleType("autograd.scipy.misc")
        shim.logsumexp = special.logsumexp
        sys.modules["autograd.scipy.misc"] = shim
        ascipy.misc = shim
    try:
        with _quiet():
            import ssm
    except ImportError:
        raise ImportError(f"The SLDS baselines need ssm: {INSTALL}") from None
    return ssm


@dataclass(frozen=True)
class Segmentation:
    """Discrete states found by a switching model.

    Attributes
    ----------
    method : str
    times : ndarray (n_times,)
    labels : ndarray of int (n_times,)
        Most likely discrete state at each sample.
    n_states : int
    log_likelihood : float
        Last value of the fit's objective (ELBO for SLDS/rSLDS, log-likelihood for the
        AR-HMM).
    """

    method: str
    times: np.ndarray = field(repr=False)
    labels: np.ndarray = field(repr=False)
    n_states: int
    log_likelihood: float

    @property
    def switch_times(self) -> np.ndarray:
        """Times at which the discrete state changes (midpoints between samples)."""
        i = np.flatnonzero(np.diff(self.labels))
        return 0.5 * (self.times[i] + self.times[i + 1])

    def accuracy(self, true_labels) -> float:
        """Share of samples labelled as in ``true_labels``, under the best matching of
        found states to true ones."""
        true = np.asarray(true_labels)
        if true.shape != self.labels.shape:
            raise ValueError(f"true_labels must have shape {self.labels.shape}; got "
                             f"{true.shape}.")
        found, f_idx = np.unique(self.labels, return_inverse=True)
        classes, c_idx = np.unique(true, return_inverse=True)
        confusion = np.zeros((found.size, classes.size))
        np.add.at(confusion, (f_idx, c_idx), 1.0)
        rows, cols = linear_sum_assignment(-confusion)  # one found state per true class
        return float(confusion[rows, cols].sum() / true.size)


def switch_time_errors(found, true) -> np.ndarray:
    """For each true switch time, the distance to the nearest found one (inf if none)."""
    found = np.asarray(found, dtype=float)
    true = np.asarray(true, dtype=float)
    if found.size == 0:
        return np.full(true.size, np.inf)
    return np.min(np.abs(true[:, None] - found[None, :]), axis=1)


def switching_lds(x, t, *, method: str = "slds", n_states: int = 2, time_input: bool = False,
                  n_iter: int = 100, seed: int = 0) -> Segmentation:
    """Segment a series with an AR-HMM, an SLDS or an rSLDS (``ssm``).

    Parameters
    ----------
    x : array (n_times, n_observed)
    t : array (n_times,) or float
        Sample times or spacing.
    method : {"slds", "rslds", "arhmm"}
    n_states : int
        Number of discrete states K.
    time_input : bool
        Give the model time (scaled to [0, 1]) as an input, as the paper tried.
    n_iter : int
        Fitting iterations (Laplace-EM for SLDS/rSLDS, EM for the AR-HMM).
    seed : int
        Seeds numpy's global generator, which ``ssm`` uses, for this call.

    Returns
    -------
    Segmentation
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS)}; got {method!r}.")
    n_states = val.check_positive(n_states, "n_states", integer=True)
    n_iter = val.check_positive(n_iter, "n_iter", integer=True)
    (data,) = one_trajectory(x, "switching_lds segments")
    (times,) = val.as_times(t, [data])
    ssm = import_ssm()
    scale = data.std(axis=0)
    scale[scale == 0] = 1.0
    y = (data - data.mean(axis=0)) / scale
    inputs = ((times - times[0]) / max(times[-1] - times[0], 1e-300))[:, None] if time_input \
        else None
    n_inputs = 1 if time_input else 0
    n_obs = y.shape[1]
    state = np.random.get_state()  # noqa: NPY002 - ssm draws from the global generator
    np.random.seed(seed)  # noqa: NPY002
    try:
        with _quiet():
            if method == "arhmm":
                model = ssm.HMM(n_states, n_obs, M=n_inputs, observations="ar")
                lls = model.fit(y, inputs=inputs, method="em", num_em_iters=n_iter)
                labels = model.most_likely_states(y, input=inputs)
            else:
                model = ssm.SLDS(n_obs, n_states, n_obs, M=n_inputs,
                                 transitions=METHODS[method], emissions="gaussian")
                lls, q = model.fit(y, inputs=inputs, method="laplace_em",
                                   variational_posterior="structured_meanfield",
                                   num_iters=n_iter, initialize=True)
                labels = model.most_likely_states(q.mean_continuous_states[0], y,
                                                  input=inputs)
    finally:
        np.random.set_state(state)  # noqa: NPY002
    return Segmentation(method, times, np.asarray(labels, dtype=int), n_states,
                        float(np.asarray(lls).ravel()[-1]))


@contextlib.contextmanager
def _quiet():
    """Silence ssm's prints, progress bars and third-party deprecation warnings."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            yield
