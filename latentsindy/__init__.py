"""latentsindy: discover hidden variables of dynamical systems with dynamic SINDy.

Public surface: :func:`discover_hidden` (observed series -> hidden states and a closed
ODE), :func:`discover_many` (many recordings or seeds in parallel),
:class:`DynamicSINDy` (stage one: time-varying SINDy coefficients), :func:`load`, the
result types, :mod:`latentsindy.systems` (test beds with known truth) and
:mod:`latentsindy.celegans` (the seed paper's C. elegans workflow and its loaders).
"""

from importlib.metadata import PackageNotFoundError, version

from . import celegans, systems
from ._batch import Run, discover_many
from ._discovery import (
    Alternative,
    HiddenComparison,
    HiddenDiscovery,
    HiddenState,
    Refinement,
    Term,
)
from ._estimator import DynamicSINDy
from ._hidden import discover_hidden
from ._persist import load
from ._results import CoefficientSeries
from ._sequential import SequentialTrainingOptions
from ._simulate import Simulation
from ._training import TrainingOptions

try:
    __version__ = version("latentsindy")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = [
    "discover_hidden",
    "discover_many",
    "Run",
    "DynamicSINDy",
    "load",
    "HiddenDiscovery",
    "HiddenComparison",
    "HiddenState",
    "Term",
    "Alternative",
    "Refinement",
    "CoefficientSeries",
    "Simulation",
    "TrainingOptions",
    "SequentialTrainingOptions",
    "systems",
    "celegans",
    "__version__",
]
