"""Dynamic HyperSINDy: a sequential hypernetwork generator for long series.

The architecture of the paper's supplementary section 1.2.2, read in time order:

* **Encoder** (VAE, four ELU layers of width 64): reads the normalised states and
  derivatives (x, xdot) at every time step; its features, pooled per chunk of 10
  steps (and over trajectories that share their dynamics) and averaged over the past
  ``context`` steps, give each chunk ``c`` a Gaussian posterior over ``z_c``
  (dimension 25). The posterior mean also has a free per-chunk offset (a
  semi-amortised posterior).
* **Hypernetwork** (an LSTM of two layers with 30 cells, or an MLP): reads the latents
  in time order and emits mixing weights ``alpha(c)``.
* **Decoder** (four ELU layers of width 256) maps ``z_c`` to SINDy coefficients with
  weights ``W(c) = W_base + sum_i alpha_i(c) D_i`` mixed from ``n_bases`` learned
  basis tensors, so the coefficient distribution drifts as the dynamics change.

Coefficients are produced per chunk and interpolated linearly to every time step.
Nothing in the network depends on the series length: the LSTM state is carried from
one window to the next, so training can run window by window (truncated
backpropagation through time) with memory set by the window, not by the series.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ._base import Generator, gaussian_kl

HYPERNETWORKS = ("lstm", "mlp")


@dataclass(frozen=True)
class HyperSINDyOptions:
    """Architecture of :class:`HyperSINDy` (defaults: the paper's table).

    Attributes
    ----------
    latent_dim : int
        Dimension of each chunk's latent z (also the hypernetwork's input).
    encoder_hidden, encoder_layers : int
        Width and depth of the per-time-step encoder (ELU).
    decoder_hidden, decoder_layers : int
        Width and number of hidden layers of the decoder (ELU).
    n_bases : int
        Number M of basis tensors D_i mixed into every decoder weight.
    hypernetwork : {"lstm", "mlp"}
        Second-level network emitting alpha(t): an LSTM (memory across time, the
        default) or an MLP of the current latent only.
    lstm_hidden, lstm_layers : int
        Cells per layer and number of layers of the LSTM (or width of the MLP).
    chunk : int
        Time steps that share one latent (the paper's "batch size (time steps)",
        1-10). Coefficients are interpolated linearly between chunk centres.
    context : int
        Time constant, in steps, of the encoder's moving average over the past: the
        stretch of data a latent summarises.
    """

    latent_dim: int = 25
    encoder_hidden: int = 64
    encoder_layers: int = 4
    decoder_hidden: int = 256
    decoder_layers: int = 4
    n_bases: int = 10
    hypernetwork: str = "lstm"
    lstm_hidden: int = 30
    lstm_layers: int = 2
    chunk: int = 10
    context: int = 500

    def __post_init__(self):
        for name in ("latent_dim", "encoder_hidden", "encoder_layers", "decoder_hidden",
                     "decoder_layers", "n_bases", "lstm_hidden", "lstm_layers", "chunk",
                     "context"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"HyperSINDyOptions.{name} must be a positive int; "
                                 f"got {value!r}.")
        if self.hypernetwork not in HYPERNETWORKS:
            raise ValueError(f"HyperSINDyOptions.hypernetwork must be one of {HYPERNETWORKS}; "
                             f"got {self.hypernetwork!r}.")


class MixedLinear(nn.Module):
    """Linear layer whose weight is ``W_base + sum_i alpha_i D_i`` (one alpha per row)."""

    def __init__(self, n_in: int, n_out: int, n_bases: int):
        super().__init__()
        self.base = nn.Linear(n_in, n_out)
        self.bases = nn.Parameter(torch.randn(n_bases, n_in, n_out) * (0.1 / n_in**0.5))
        self.bias_bases = nn.Parameter(torch.zeros(n_bases, n_out))

    def forward(self, h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        # sum_i alpha_i (h D_i) as one matmul of (alpha outer h) with the stacked bases
        mixed = (alpha[..., :, None] * h[..., None, :]).flatten(-2)
        return (self.base(h) + mixed @ self.bases.flatten(0, 1) + alpha @ self.bias_bases)


class HyperSINDy(Generator):
    """Per-chunk VAE encoder -> hypernetwork alpha(t) -> weight-mixing decoder.

    Examples
    --------
    >>> import torch
    >>> g = HyperSINDy(n_inputs=4, n_outputs=6, options=HyperSINDyOptions())
    >>> series, kl = g.sample(torch.randn(1, 4, 1000), n_samples=3)
    >>> tuple(series.shape)
    (3, 1000, 6)
    """

    Options = HyperSINDyOptions
    sequential = True

    def __init__(self, n_inputs: int, n_outputs: int, options: HyperSINDyOptions):
        super().__init__()
        o = self.options = options
        self.chunk = o.chunk
        self.window_len = 1000  # steps per window; the trainer sets it
        self.codes = None  # per-chunk free offsets of the latent means, see allocate()
        self.chunk_var = None  # per-chunk prior variance of latent changes, see allocate()
        layers: list[nn.Module] = []
        width = n_inputs
        for _ in range(o.encoder_layers - 1):
            layers += [nn.Linear(width, o.encoder_hidden), nn.ELU()]
            width = o.encoder_hidden
        self.encoder = nn.Sequential(*layers)
        self.to_latent = nn.Linear(2 * width, 2 * o.latent_dim)
        if o.hypernetwork == "lstm":
            self.lstm = nn.LSTM(o.latent_dim, o.lstm_hidden, o.lstm_layers, batch_first=True)
            self.mlp = None
        else:
            self.lstm = None
            self.mlp = nn.Sequential(nn.Linear(o.latent_dim, o.lstm_hidden), nn.ELU())
        self.to_alpha = nn.Linear(o.lstm_hidden, o.n_bases)
        dims = [o.latent_dim] + [o.decoder_hidden] * o.decoder_layers + [n_outputs]
        self.decoder = nn.ModuleList(MixedLinear(a, b, o.n_bases)
                                     for a, b in zip(dims[:-1], dims[1:], strict=True))
        # Start from "no time variation": the estimator's constants carry the initial fit.
        last = self.decoder[-1]
        nn.init.zeros_(last.base.weight)
        nn.init.zeros_(last.base.bias)
        nn.init.zeros_(last.bases)

    # ---------------------------------------------------------------- pieces
    def allocate(self, n_times: int, positions: torch.Tensor | None = None) -> None:
        """Create the per-chunk offsets for a series of ``n_times`` steps (zeros).

        The posterior mean of chunk ``c`` is the encoder's window latent plus a free
        offset ``delta_c`` (a semi-amortised posterior): the encoder supplies what the
        window's data say, the offsets let every chunk be fitted directly, as timeVAE's
        decoder fits its knots. Sparse gradients: a step touches only its window's rows.

        With irregular ``positions`` (see :meth:`Generator.allocate`) a chunk's
        coefficients sit at its time centre, and the random-walk prior of the latents
        lets them change in proportion to the time between chunk centres (per unit
        time, not per sample).
        """
        super().allocate(n_times, positions)
        n_chunks = -(-n_times // self.chunk)
        self.codes = nn.Embedding(n_chunks, self.options.latent_dim, sparse=True)
        nn.init.zeros_(self.codes.weight)
        self.chunk_var = None
        if positions is not None:
            centres = chunk_centres(0, n_times, self.chunk, positions.dtype, positions.device,
                                    positions)
            gaps = torch.diff(centres) / self.chunk
            self.chunk_var = torch.cat([gaps.new_ones(1), gaps.clamp_min(1e-3)])

    def encode(self, inputs: torch.Tensor, memory=None):
        """(B, C_in, W) -> posterior means and log-variances per chunk, and the memory.

        Per-step features of (x, xdot) are pooled per chunk (and over trajectories),
        then averaged over the past with an exponential moving average of time constant
        ``context`` steps, carried from window to window (bias-corrected at the start).
        The latent thus summarises the recent stretch of data, not the current state,
        and changes smoothly across window boundaries.
        """
        h = self.encoder(inputs.transpose(1, 2)).mean(dim=0)  # (W, H)
        feats = torch.cat([h, h * h], dim=-1)
        n_steps, chunk = feats.shape[0], self.chunk
        n_chunks = -(-n_steps // chunk)
        index = torch.arange(n_steps, device=h.device) // chunk
        sums = torch.zeros(n_chunks, feats.shape[1], dtype=h.dtype, device=h.device)
        sums.index_add_(0, index, feats)
        counts = torch.bincount(index, minlength=n_chunks).to(h.dtype)[:, None]
        per_chunk = (sums / counts).double()
        decay = math.exp(-chunk / self.options.context)
        k = torch.arange(n_chunks, device=h.device, dtype=torch.float64)
        if memory is None:
            memory = (torch.zeros_like(per_chunk[0]), per_chunk.new_zeros(()))
        ema0, norm0 = memory
        # e_c = decay^(c+1) e_{-1} + (1 - decay) sum_{j<=c} decay^(c-j) f_j, in closed form
        grow = decay ** (-k)
        scan = torch.cumsum(per_chunk * grow[:, None], dim=0)
        ema = decay ** (k + 1)[:, None] * ema0 + (1 - decay) * decay ** k[:, None] * scan
        norm = decay ** (k + 1) * norm0 + (1 - decay ** (k + 1))
        mean_sq = (ema / norm[:, None]).float()
        width = h.shape[1]
        mean, sq = mean_sq[:, :width], mean_sq[:, width:]
        pooled = torch.cat([mean, (sq - mean * mean).clamp_min(0).add(1e-8).sqrt()], dim=-1)
        mu, logvar = self.to_latent(pooled).chunk(2, dim=-1)
        return mu, logvar.clamp(-12.0, 6.0), (ema[-1], norm[-1])

    def chunk_offsets(self, start: int, n_steps: int, like: torch.Tensor) -> torch.Tensor:
        """Free offsets (n_chunks, latent) of the chunks of steps [start, start + n_steps)."""
        first = start // self.chunk
        n_chunks = -(-n_steps // self.chunk)
        if self.codes is None:
            return torch.zeros(n_chunks, self.options.latent_dim, dtype=like.dtype,
                               device=like.device)
        index = torch.arange(first, first + n_chunks, device=like.device)
        inside = index < self.codes.num_embeddings
        out = self.codes(index.clamp(max=self.codes.num_embeddings - 1))
        return out * inside[:, None].to(out.dtype)

    def mixing(self, z: torch.Tensor, state):
        """Latents (S, C, latent) -> alpha (S, C, n_bases) and the carried state."""
        if self.lstm is None:
            return self.to_alpha(self.mlp(z)), None
        out, state = self.lstm(z, state)
        return self.to_alpha(out), state

    def decode(self, z: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        h = z
        for k, layer in enumerate(self.decoder):
            h = layer(h, alpha)
            if k < len(self.decoder) - 1:
                h = F.elu(h)
        return h

    # -------------------------------------------------------------- interface
    def window(self, inputs: torch.Tensor, n_samples: int, state=None, start: int = 0):
        """One window in time order: chunk coefficients (S, C, n_out), KL, new state.

        ``start`` is the window's first step in the series (it selects the chunk
        offsets); ``state`` is the hypernetwork state at the window's start (``None``:
        zeros); the returned state continues into the next window.
        """
        lstm_state, memory, last = state if state is not None else (None, None, None)
        mu_enc, logvar, memory = self.encode(inputs, memory)
        mu = mu_enc + self.chunk_offsets(start, inputs.shape[-1], mu_enc)
        if n_samples == 0:
            z = mu[None]
        else:
            eps = torch.randn((n_samples, *mu.shape), dtype=mu.dtype, device=mu.device)
            z = mu[None] + eps * torch.exp(0.5 * logvar)[None]
        alpha, lstm_state = self.mixing(z, lstm_state)
        # random-walk prior z_c ~ N(mean of z_{c-1}, 1), z_0 ~ N(0, 1): the KL charges
        # for changes of the latent, not for its size
        before = torch.zeros_like(mu[:1]) if last is None else last[None]
        prior = None
        if self.chunk_var is not None:  # irregular times: changes scale with the time
            first = start // self.chunk
            prior = self.chunk_var[first:first + mu.shape[0], None]
        kl = gaussian_kl(mu - torch.cat([before, mu[:-1]]), logvar, prior)
        return self.decode(z, alpha), kl, (lstm_state, memory, mu[-1])

    def sample(self, inputs: torch.Tensor, n_samples: int, window: int | None = None):
        """Whole series, read window by window: (S, T, n_out) and the total KL."""
        window = window or self.window_len
        window = max(self.chunk, window - window % self.chunk)
        state, parts, kl = None, [], 0.0
        for start in range(0, inputs.shape[-1], window):
            series, kl_w, state = self.window(inputs[..., start:start + window], n_samples,
                                              state, start)
            parts.append(series)
            kl = kl + kl_w
        return interpolate_chunks(torch.cat(parts, dim=1), inputs.shape[-1], self.chunk,
                                  self.positions), kl


def detach_state(state):
    """Cut the graph behind a carried state (truncated backpropagation through time)."""
    if state is None:
        return None
    if isinstance(state, tuple):
        return tuple(detach_state(s) for s in state)
    return state.detach()


def chunk_centres(start: int, stop: int, chunk: int, dtype=torch.float32, device=None,
                  positions=None):
    """Centres of the chunks of steps [start, stop) (the last chunk may be short): the
    middle of each chunk's first and last step, in steps, or in ``positions`` (the
    sample times in mean steps) when given."""
    lo = torch.arange(start, stop, chunk, dtype=dtype, device=device)
    hi = torch.clamp(lo + chunk, max=stop)
    if positions is None:
        return (lo + hi - 1) / 2
    return (positions[lo.long()] + positions[hi.long() - 1]) / 2


def interpolate_at(values: torch.Tensor, centres: torch.Tensor,
                   steps: torch.Tensor) -> torch.Tensor:
    """Values (S, K, M) at ``centres`` (K,) -> (S, len(steps), M), linear in between and
    constant beyond the first and last centre."""
    if values.shape[1] == 1:
        return values.expand(-1, steps.shape[0], -1)
    pos = torch.searchsorted(centres, steps).clamp(1, values.shape[1] - 1)
    left, right = centres[pos - 1], centres[pos]
    frac = ((steps - left) / (right - left)).clamp(0.0, 1.0)[None, :, None]
    return values[:, pos - 1] * (1 - frac) + values[:, pos] * frac


def interpolate_chunks(values: torch.Tensor, n_steps: int, chunk: int,
                       positions=None) -> torch.Tensor:
    """Chunk values (S, C, K) -> per-step values (S, n_steps, K), linear in time between
    chunk centres (``positions``: sample times in mean steps; None: uniform)."""
    centres = chunk_centres(0, n_steps, chunk, values.dtype, values.device, positions)
    steps = (torch.arange(n_steps, dtype=values.dtype, device=values.device)
             if positions is None else positions.to(values.dtype))
    return interpolate_at(values, centres, steps)
