"""latentsindy: discover hidden variables of dynamical systems with dynamic SINDy.

The verbs and the main classes live here:

* :func:`discover_hidden`: an observed series to hidden states and a closed ODE
  (:class:`HiddenDiscovery`);
* :func:`discover_many`: many recordings or seeds in parallel, locally or on a Dask
  cluster (one :class:`Run` each);
* :class:`DynamicSINDy`: stage one alone, time-varying SINDy coefficients
  (:class:`CoefficientSeries`);
* :func:`load`: a saved result or fitted model.

Namespaces: :mod:`latentsindy.results` (the result types and their parts),
:mod:`latentsindy.options` (stage one's options), :mod:`latentsindy.systems` (test beds
with known truth), :mod:`latentsindy.generators` (stage one's deep generative models),
:mod:`latentsindy.celegans` (the C. elegans workflow) and :mod:`latentsindy.baselines`
(the paper's baselines).
"""

import warnings as _warnings
from importlib.metadata import PackageNotFoundError as _PackageNotFoundError
from importlib.metadata import version as _version

from . import baselines, celegans, generators, options, results, systems
from ._batch import Run, discover_many
from ._files.load import load  # also registers the file formats with _core.saving
from ._stage_one.coefficients import CoefficientSeries
from ._stage_one.estimator import DynamicSINDy
from ._stage_two.discover import discover_hidden
from ._stage_two.result import HiddenDiscovery

try:
    __version__ = _version("latentsindy")
except _PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

# Names that 0.1 exported from the top level and 0.2 keeps in a namespace: still
# importable from here, with a warning that names the new place.
_MOVED = {
    "HiddenComparison": "results", "HiddenState": "results", "Term": "results",
    "Alternative": "results", "Refinement": "results", "DataUse": "results",
    "Simulation": "results", "TrainingOptions": "options",
    "SequentialTrainingOptions": "options",
}


def __getattr__(name):
    if name in _MOVED:
        where = _MOVED[name]
        _warnings.warn(f"latentsindy.{name} moved to latentsindy.{where}.{name} in 0.2; "
                      f"import it from there (from latentsindy.{where} import {name}).",
                      DeprecationWarning, stacklevel=2)
        return getattr(globals()[where], name)
    raise AttributeError(f"module 'latentsindy' has no attribute {name!r}")


__all__ = [
    "discover_hidden",
    "discover_many",
    "DynamicSINDy",
    "load",
    "HiddenDiscovery",
    "CoefficientSeries",
    "Run",
    "results",
    "options",
    "systems",
    "generators",
    "celegans",
    "baselines",
    "__version__",
]
