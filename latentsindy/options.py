"""Options of stage one, each a frozen dataclass validated once, when it is made.

* :class:`TrainingOptions`: how timeVAE is trained (``DynamicSINDy(training=...)``);
* :class:`SequentialTrainingOptions`: how dynamic HyperSINDy is trained, window by
  window (``DynamicSINDy(generator="hypersindy", training=...)``);
* :class:`TimeVAEOptions`, :class:`HyperSINDyOptions`: the generators' architectures
  (``DynamicSINDy(generator_options=...)``).

A dict with the same keys is accepted wherever an options object is; a misspelt key is
an error that lists the valid ones.
"""

from ._stage_one.sequential_options import SequentialTrainingOptions
from ._stage_one.training import TrainingOptions
from .generators import HyperSINDyOptions, TimeVAEOptions

__all__ = [
    "TrainingOptions",
    "SequentialTrainingOptions",
    "TimeVAEOptions",
    "HyperSINDyOptions",
]
