"""latentsindy: discover hidden variables of dynamical systems with dynamic SINDy."""

from importlib.metadata import PackageNotFoundError, version

from . import systems
from ._estimator import DynamicSINDy
from ._results import CoefficientSeries
from ._training import TrainingOptions

try:
    __version__ = version("latentsindy")
except PackageNotFoundError:  # pragma: no cover - running from a source tree
    __version__ = "0.0.0"

__all__ = ["DynamicSINDy", "CoefficientSeries", "TrainingOptions", "systems", "__version__"]
