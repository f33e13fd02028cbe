"""timeVAE: a convolutional VAE from a whole series to its coefficient series.

Encoder: strided 1-D convolutions over the normalised states and derivatives, pooled
over time (and over trajectories that share their dynamics) into a Gaussian latent z.
A series longer than ``n_knots`` samples is first averaged down to ``n_knots`` points:
the encoder only summarises the whole series into one latent, which needs no finer
time resolution than the decoder's, so its cost stops growing with the length.
Decoder: the timeVAE pattern (dense -> reshape -> upsampling convolutions) produces
the coefficients on a fixed grid of ``n_knots`` points spanning the series, which is
interpolated linearly to every time step.

Two properties the paper's reference code lacked:

* the parameter count does not depend on the series length (the reference's final
  dense layer had (T*F)^2 weights) and memory grows linearly with it;
* the decoder sees only z, never x(t) itself, so a coefficient cannot quietly become
  a function of the state (which would make the library meaningless): Xi depends on
  time and on the series as a whole.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ._base import Generator, gaussian_kl


@dataclass(frozen=True)
class TimeVAEOptions:
    """Architecture of :class:`TimeVAE`.

    Attributes
    ----------
    latent_dim : int
        Dimension of the latent z.
    hidden : int
        Channels of the hidden convolutions.
    kernel_size : int
        Odd kernel width of every convolution.
    n_knots : int or None
        Resolution of the decoded coefficients: points across the series, a power
        of two >= 32 (256 resolves a switch to 0.4% of the series). The encoder reads
        a longer series averaged down to this many points. None (default): what the
        data resolve (:func:`knots_for`), chosen by the estimator from the noise of the
        states x (given derivatives do not change it: the exact model's grid is the
        same); a :class:`TimeVAE` built directly with None gets ``MAX_KNOTS``.
    """

    latent_dim: int = 4
    hidden: int = 32
    kernel_size: int = 5
    n_knots: int | None = None

    def __post_init__(self):
        for name in ("latent_dim", "hidden", "kernel_size", "n_knots"):
            value = getattr(self, name)
            if name == "n_knots":
                continue
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"TimeVAEOptions.{name} must be a positive int; got {value!r}.")
        if self.kernel_size % 2 == 0:
            raise ValueError(f"TimeVAEOptions.kernel_size must be odd; got {self.kernel_size}.")
        k = self.n_knots
        if k is not None and (not isinstance(k, int) or isinstance(k, bool) or k < 32
                              or k & (k - 1)):
            raise ValueError(f"TimeVAEOptions.n_knots must be a power of two >= 32, or None "
                             f"(chosen from the data); got {k!r}.")


_BASE = 32  # knots produced by the dense layer before upsampling
MAX_KNOTS = 256  # the most knots chosen from the data


def knots_for(intervals: float) -> int:
    """The decoder's knots for a series whose coefficients the data resolve on
    ``intervals`` intervals (the exact model's: one every half differentiator window,
    :func:`latentsindy._stage_one.evidence.resolution`): the smallest power of two
    with at least that many intervals, between ``_BASE`` and ``MAX_KNOTS``.

    A coefficient cannot be resolved more finely than the derivatives it is fitted to
    (the differentiator smooths them over its window), and stage two's smoother
    re-estimates every hidden series on that grid; knots beyond it only add
    convolution layers to every training step (prey-only Lotka-Volterra at 1% noise
    resolves about 60 intervals: 64 knots, one upsampling convolution where 256 needed
    three). Noise-free series of about 600 samples and more resolve more than 255
    intervals and keep ``MAX_KNOTS`` (shorter ones get fewer).

    >>> knots_for(60.2), knots_for(64), knots_for(5000), knots_for(3)
    (64, 128, 256, 32)
    """
    knots = _BASE
    while knots - 1 < intervals and knots < MAX_KNOTS:
        knots *= 2
    return knots


class TimeVAE(Generator):
    """Convolutional encoder -> latent z -> dense + upsampling-convolution decoder.

    Examples
    --------
    >>> import torch
    >>> g = TimeVAE(n_inputs=4, n_outputs=6, options=TimeVAEOptions())
    >>> series, kl = g.sample(torch.randn(1, 4, 1000), n_samples=3)
    >>> tuple(series.shape)
    (3, 1000, 6)
    """

    Options = TimeVAEOptions

    def __init__(self, n_inputs: int, n_outputs: int, options: TimeVAEOptions):
        super().__init__()
        if options.n_knots is None:
            options = dataclasses.replace(options, n_knots=MAX_KNOTS)
        o = options
        self.options = options
        pad = o.kernel_size // 2
        width, layers = n_inputs, []
        for _ in range(3):
            layers += [nn.Conv1d(width, o.hidden, o.kernel_size, stride=2, padding=pad), nn.GELU()]
            width = o.hidden
        self.encoder = nn.Sequential(*layers)
        self.to_latent = nn.Linear(2 * o.hidden, 2 * o.latent_dim)
        self.from_latent = nn.Linear(o.latent_dim, o.hidden * _BASE)
        ups: list[nn.Module] = []
        for _ in range((o.n_knots // _BASE).bit_length() - 1):
            ups += [nn.Upsample(scale_factor=2, mode="linear", align_corners=False),
                    nn.Conv1d(o.hidden, o.hidden, o.kernel_size, padding=pad), nn.GELU()]
        self.upsample = nn.Sequential(*ups)
        self.to_coefficients = nn.Conv1d(o.hidden, n_outputs, 1)
        # points the encoder reads (a longer series is averaged down to them); None reads
        # every sample, as models saved before model-file version 3 were trained to
        self.encoder_points = o.n_knots
        # Start from "no time variation": the estimator's constants carry the initial fit.
        nn.init.zeros_(self.to_coefficients.weight)
        nn.init.zeros_(self.to_coefficients.bias)

    @classmethod
    def for_data(cls, options: TimeVAEOptions, intervals: float) -> TimeVAEOptions:
        """``n_knots`` from the data (:func:`knots_for`) where the options leave it None."""
        if options.n_knots is not None:
            return options
        return dataclasses.replace(options, n_knots=knots_for(intervals))

    def encode(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Posterior mean and log-variance of z, pooled over time and trajectories."""
        # the series at the decoder's resolution: on 2000 samples the encoder's
        # convolutions were a third of each training step, with the same accuracy
        if self.encoder_points is not None and inputs.shape[-1] > self.encoder_points:
            inputs = F.adaptive_avg_pool1d(inputs, self.encoder_points)
        h = self.encoder(inputs)
        pooled = torch.cat([h.mean(dim=-1), h.std(dim=-1)], dim=-1).mean(dim=0)
        mu, logvar = self.to_latent(pooled).chunk(2, dim=-1)
        return mu, logvar.clamp(-12.0, 6.0)

    def decode(self, z: torch.Tensor, n_times: int) -> torch.Tensor:
        """Latents (S, latent_dim) -> series (S, n_times, n_outputs): knots equally
        spaced in time, interpolated linearly to the sample times (``allocate``)."""
        h = F.gelu(self.from_latent(z)).reshape(z.shape[0], self.options.hidden, _BASE)
        knots = self.to_coefficients(self.upsample(h))
        if self.positions is None or len(self.positions) != n_times:
            return F.interpolate(knots, size=n_times, mode="linear",
                                 align_corners=True).transpose(1, 2)
        # knot k sits at position k (n_times - 1) / (n_knots - 1), whatever the sampling
        where = self.positions * ((knots.shape[-1] - 1) / max(n_times - 1, 1))
        left = where.floor().long().clamp(0, knots.shape[-1] - 2)
        frac = (where - left.to(where.dtype))[None, :, None]
        knots = knots.transpose(1, 2)
        return knots[:, left] * (1 - frac) + knots[:, left + 1] * frac

    def sample(self, inputs: torch.Tensor, n_samples: int) -> tuple[torch.Tensor, torch.Tensor]:
        mu, logvar = self.encode(inputs)
        if n_samples == 0:
            z = mu[None]
        else:
            eps = torch.randn((n_samples, *mu.shape), dtype=mu.dtype, device=mu.device)
            z = mu[None] + eps * torch.exp(0.5 * logvar)[None]
        return self.decode(z, inputs.shape[-1]), gaussian_kl(mu, logvar)
