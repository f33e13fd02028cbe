"""Stage one's deep generative models: a normalised series to coefficient series.

Public because it is the extension point: a new generator implements
:meth:`Generator.sample` and is registered in ``GENERATORS``; everything else (library,
masks, constants, loss, pruning) belongs to the estimator in ``latentsindy._stage_one``.
``timevae`` reads the whole series at once, ``hypersindy`` (dynamic HyperSINDy) window
by window.
"""

from ._base import Generator, make_options
from .hypersindy import HyperSINDy, HyperSINDyOptions
from .timevae import TimeVAE, TimeVAEOptions

GENERATORS: dict[str, type[Generator]] = {"timevae": TimeVAE, "hypersindy": HyperSINDy}


def generator_class(name: str) -> type[Generator]:
    """The generator class registered as ``name``; an unknown name is an error."""
    if not isinstance(name, str) or name not in GENERATORS:
        raise ValueError(f"generator must be one of {sorted(GENERATORS)}; got {name!r}.")
    return GENERATORS[name]


def build_generator(name: str, n_inputs: int, n_outputs: int, options,
                    intervals: float | None = None) -> Generator:
    """Instantiate the generator ``name`` with validated options (the caller seeds torch);
    with ``intervals`` (the resolution of the data, :meth:`Generator.for_data`) what the
    options leave to the data is chosen from it. The options used are ``.options``."""
    cls = generator_class(name)
    options = make_options(cls.Options, options, name)
    if intervals is not None:
        options = cls.for_data(options, intervals)
    return cls(n_inputs, n_outputs, options)


__all__ = ["Generator", "TimeVAE", "TimeVAEOptions", "HyperSINDy", "HyperSINDyOptions",
           "GENERATORS", "generator_class", "build_generator"]
