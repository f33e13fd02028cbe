"""What latentsindy returns: results and their parts.

* :class:`HiddenDiscovery`, from :func:`~latentsindy.discover_hidden`: observed plus
  hidden states and their closed ODE, with the checks it passed and failed;
* :class:`CoefficientSeries`, from :meth:`DynamicSINDy.coefficients
  <latentsindy.DynamicSINDy.coefficients>`: stage one's time-varying coefficients with
  their band;
* :class:`Run`, one discovery of :func:`~latentsindy.discover_many`;
* the parts: :class:`HiddenState`, :class:`Term`, :class:`Alternative`,
  :class:`Refinement`, :class:`HiddenComparison`, :class:`DataUse`,
  :class:`Simulation` and :class:`Doubt` (a failed check: a kind and a sentence).

All are frozen: a result is a record of what was found, not something to edit.
"""

from ._batch import Run
from ._core.doubt import Doubt
from ._core.recordings import DataUse
from ._core.simulate import Simulation
from ._stage_one.coefficients import CoefficientSeries
from ._stage_two.result import HiddenDiscovery
from ._stage_two.result_parts import (
    Alternative,
    HiddenComparison,
    HiddenState,
    Refinement,
    Term,
)

__all__ = [
    "HiddenDiscovery",
    "CoefficientSeries",
    "Run",
    "HiddenState",
    "Term",
    "Alternative",
    "Refinement",
    "HiddenComparison",
    "DataUse",
    "Simulation",
    "Doubt",
]
