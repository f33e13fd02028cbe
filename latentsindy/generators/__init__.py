"""Coefficient generators (stage one's deep generative models)."""

import torch

from ._base import Generator, make_options
from .timevae import TimeVAE, TimeVAEOptions

GENERATORS: dict[str, type[Generator]] = {"timevae": TimeVAE}


def build_generator(name: str, n_inputs: int, n_outputs: int, options, seed: int) -> Generator:
    """Instantiate the generator ``name`` with validated options and seeded weights."""
    if name not in GENERATORS:
        raise ValueError(f"generator must be one of {sorted(GENERATORS)}; got {name!r}.")
    cls = GENERATORS[name]
    opts = make_options(cls.Options, options, name)
    torch.manual_seed(seed)  # callers wrap this in a forked RNG
    return cls(n_inputs, n_outputs, opts)


__all__ = ["Generator", "TimeVAE", "TimeVAEOptions", "GENERATORS", "build_generator"]
