"""Coefficient generators (stage one's deep generative models)."""

from ._base import Generator, make_options
from .timevae import TimeVAE, TimeVAEOptions

GENERATORS: dict[str, type[Generator]] = {"timevae": TimeVAE}


def build_generator(name: str, n_inputs: int, n_outputs: int, options) -> Generator:
    """Instantiate the generator ``name`` with validated options (the caller seeds torch)."""
    if name not in GENERATORS:
        raise ValueError(f"generator must be one of {sorted(GENERATORS)}; got {name!r}.")
    cls = GENERATORS[name]
    return cls(n_inputs, n_outputs, make_options(cls.Options, options, name))


__all__ = ["Generator", "TimeVAE", "TimeVAEOptions", "GENERATORS", "build_generator"]
