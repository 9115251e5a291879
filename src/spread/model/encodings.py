"""Fixed encodings: sinusoidal codes of integers / timesteps, Fourier features of coordinates.

All are parameter-free functions of their input (the learned MLPs that follow them live with their
users), batched over any leading dimensions.
"""

from __future__ import annotations

import math

import torch
from einops import rearrange
from torch import nn


def sinusoidal_embedding(positions: torch.Tensor, dim: int, base: float = 10_000.0) -> torch.Tensor:
    """Transformer sinusoids of (...,) integer or real positions → (..., dim) float.

    Channel 2k is ``sin(p / base^(2k/dim))`` and 2k+1 its cosine (Vaswani et al. 2017), the code
    the reference uses for object indices and timesteps. ``dim`` must be even.
    """
    if dim % 2:
        raise ValueError(f"sinusoidal_embedding: dim must be even, got {dim}")
    half = dim // 2
    freqs = torch.exp(-math.log(base) * torch.arange(half, device=positions.device, dtype=torch.float32) / half)
    angles = positions.float()[..., None] * freqs
    return rearrange(torch.stack([angles.sin(), angles.cos()], dim=-1), "... k two -> ... (k two)")


def fourier_features(x: torch.Tensor, num_bands: int, max_frequency: float) -> torch.Tensor:
    """(..., C) coordinates → (..., C·(2·num_bands + 1)) = [x, sin(π f x), cos(π f x)] per channel.

    Frequencies ``f`` are log-spaced from 1 to ``max_frequency`` (cycles per unit of x), so a
    coordinate in metres with ``max_frequency=64`` resolves features of about 1.5 cm.
    """
    freqs = torch.logspace(0.0, math.log10(max_frequency), num_bands, device=x.device, dtype=x.dtype)
    angles = math.pi * x[..., None] * freqs  # (..., C, F)
    feats = torch.cat([x[..., None], angles.sin(), angles.cos()], dim=-1)
    return rearrange(feats, "... c f -> ... (c f)")


def fourier_dim(channels: int, num_bands: int) -> int:
    """Output width of :func:`fourier_features`."""
    return channels * (2 * num_bands + 1)


class TimestepEmbedding(nn.Module):
    """Diffusion timestep t (B,) in [0, 1000) → (B, dim): sinusoids(t, freq_dim) → Linear → SiLU → Linear."""

    def __init__(self, dim: int, freq_dim: int = 128):
        super().__init__()
        self.freq_dim = freq_dim
        self.mlp = nn.Sequential(nn.Linear(freq_dim, dim), nn.SiLU(), nn.Linear(dim, dim))

    def forward(self, t: torch.Tensor) -> torch.Tensor:
        return self.mlp(sinusoidal_embedding(t, self.freq_dim))
