"""The interface every coefficient generator implements, and the registry of generators.

A generator is a ``torch.nn.Module`` that reads normalised trajectories and emits
time-varying coefficient series. The estimator owns everything else (library, masks,
constants, loss, pruning), so a new generator only has to implement :meth:`sample`.
"""

from __future__ import annotations

import dataclasses

import torch
from torch import nn


class Generator(nn.Module):
    """Base class: ``sample(inputs, n_samples)`` -> (series, kl).

    A call ``sample(inputs, n_samples)`` takes these and returns the series and KL below.

    Parameters
    ----------
    inputs : Tensor, shape (n_trajectories, n_channels, n_times)
        Normalised states and derivatives of trajectories that share one set of
        time-varying dynamics.
    n_samples : int
        Number of posterior draws; ``0`` returns the posterior mean (one series).

    Returns
    -------
    series : Tensor, shape (max(n_samples, 1), n_times, n_outputs)
    kl : Tensor, scalar
        KL divergence of the approximate posterior from the prior, summed over all
        latent elements (the ELBO's KL term).
    """

    Options: type = object
    sequential = False  # True: trained window by window (see latentsindy._stage_one.sequential)
    positions: torch.Tensor | None = None  # sample times, see allocate()
    spacing: torch.Tensor | None = None

    @classmethod
    def for_data(cls, options, intervals: float):
        """``options`` with what they leave to the data filled in, for a series whose
        coefficients the data resolve on ``intervals`` intervals (one every half
        differentiator window). The default leaves them as they are."""
        return options

    def allocate(self, n_times: int, positions: torch.Tensor | None = None) -> None:
        """Prepare for a series of ``n_times`` samples (the estimator calls this first).

        ``positions`` (n_times,) are the sample times in units of the mean step from
        the first sample, or None for a uniform grid (where they are the sample
        indices): coefficients are laid out in time, not by sample, so an irregularly
        sampled series gets the same coefficient curve as a uniform one.
        """
        self.positions = positions
        self.spacing = None if positions is None else torch.diff(positions)

    def sample(self, inputs: torch.Tensor, n_samples: int) -> tuple[torch.Tensor, torch.Tensor]:
        raise NotImplementedError


def make_options(options_cls, given, generator: str):
    """Build a generator's frozen options from a dict, None or the options themselves
    (a fitted estimator's ``generator_options_``); a misspelt option is an error."""
    if isinstance(given, options_cls):
        return given
    if dataclasses.is_dataclass(given) and not isinstance(given, type):
        raise TypeError(f"generator {generator!r} takes {options_cls.__name__} or a dict as "
                        f"options; got {type(given).__name__}.")
    given = dict(given or {})
    fields = {f.name for f in dataclasses.fields(options_cls)}
    unknown = sorted(set(given) - fields)
    if unknown:
        raise TypeError(
            f"Unknown option(s) {unknown} for generator {generator!r}; "
            f"valid options are {sorted(fields)}."
        )
    return options_cls(**given)


def gaussian_kl(mu: torch.Tensor, logvar: torch.Tensor, prior_var=None) -> torch.Tensor:
    """KL(N(mu, exp(logvar)) || N(0, prior_var)) (prior variance 1 by default), summed
    over all latent elements; ``prior_var`` broadcasts against ``mu``."""
    if prior_var is None:
        return 0.5 * torch.sum(mu.pow(2) + logvar.exp() - 1.0 - logvar)
    return 0.5 * torch.sum((mu.pow(2) + logvar.exp()) / prior_var - 1.0 - logvar
                           + torch.log(prior_var))
