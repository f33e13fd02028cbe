"""latentsindy: discover hidden variables of dynamical systems with dynamic SINDy.

Public surface: :func:`discover_hidden` (observed series -> hidden states and a closed
ODE), :func:`discover_many` (many recordings or seeds in parallel),
:class:`DynamicSINDy` (stage one: time-varying SINDy coefficients), :func:`load`, the
result types, :mod:`latentsindy.systems` (test beds with known truth) and
:mod:`latentsindy.celegans` (the seed paper's C. elegans workflow and its loaders).
"""

from importlib.metadata import PackageNotFoundError, version

from . import celegans, systems
from ._cli.batch import Run, discover_many
from ._core.recordings import DataUse
from ._core.simulate import Simulation
from ._files.load import load  # also registers the file formats with _core.saving
from ._stage_one.coefficients import CoefficientSeries
from ._stage_one.estimator import DynamicSINDy
from ._stage_one.sequential_options import SequentialTrainingOptions
from ._stage_one.training import TrainingOptions
from ._stage_two.discover import discover_hidden
from ._stage_two.result import (
    Alternative,
    HiddenComparison,
    HiddenDiscovery,
    HiddenState,
    Refinement,
    Term,
)

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
    "DataUse",
    "CoefficientSeries",
    "Simulation",
    "TrainingOptions",
    "SequentialTrainingOptions",
    "systems",
    "celegans",
    "__version__",
]
