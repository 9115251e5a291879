"""Geometry perceiver: signed chamfer point features of the whole scene → a few scene-level tokens.

Input: ``features`` (B, N, M, 4) from :func:`spread.model.geometry.signed_chamfer_features`
([canonical xyz (m), signed distance (m)]) and ``mask`` (B, N). Output: (B, num_latents, dim) tokens,
shared by the scene (as the release: 256 latents for all objects), that every object node attends to.

Point token (one per point of every real object, padding objects' points are masked out of the
attention), all fixed encodings concatenated and fed to the cross-attention's key/value projection:

* Fourier features of the canonical xyz — *where on the object* the point is. (The release encodes
  the point's index instead; with randomly drawn points that index carries no geometry.)
* the signed distance ``d`` itself and ``tanh(d / s)`` for s in ``DISTANCE_SCALES`` — fine
  resolution around contact (mm–cm) without losing the far field (m).
* a sinusoidal code of the object index — *which object* the point belongs to; the denoiser gives
  each node the same code, which is how a node finds its own points in the shared latents.

Then ``depth`` × [cross-attention latents ← point tokens, ``self_per_cross`` × self-attention],
each with a GEGLU feed-forward, pre-LayerNorm and residuals (Perceiver, Jaegle et al. 2021). The
latents' norms are plain LayerNorms: the features already depend on the timestep through the noisy
poses, and the denoiser's adaptive norms read the tokens.
"""

from __future__ import annotations

import torch
from einops import rearrange, repeat
from torch import nn

from spread.model.encodings import fourier_dim, fourier_features, sinusoidal_embedding
from spread.model.layers import Attention, FeedForward

#: Length scales (metres) of the squashed signed-distance channels.
DISTANCE_SCALES = (0.01, 0.05, 0.25)


def point_tokens(features: torch.Tensor, num_bands: int, max_frequency: float, index_dim: int) -> torch.Tensor:
    """(B, N, M, 4) chamfer features → (B, N·M, point_token_dim(...)) fixed encodings (module docstring)."""
    B, N, M, _ = features.shape
    xyz, d = features[..., :3], features[..., 3:4]
    squashed = [torch.tanh(d / s) for s in DISTANCE_SCALES]
    index = sinusoidal_embedding(torch.arange(N, device=features.device), index_dim)  # (N, E)
    index = repeat(index, "n e -> b n m e", b=B, m=M)
    tokens = torch.cat([fourier_features(xyz, num_bands, max_frequency), d, *squashed, index], dim=-1)
    return rearrange(tokens, "b n m c -> b (n m) c")


def point_token_dim(num_bands: int, index_dim: int) -> int:
    return fourier_dim(3, num_bands) + 1 + len(DISTANCE_SCALES) + index_dim


class GeometryPerceiver(nn.Module):
    """Chamfer features (B, N, M, 4), mask (B, N) → scene geometry tokens (B, num_latents, dim)."""

    def __init__(self, dim: int, num_latents: int = 256, depth: int = 4, self_per_cross: int = 2,
                 cross_heads: int = 1, cross_dim_head: int = 64, heads: int = 8, dim_head: int = 64,
                 ff_mult: int = 4, num_bands: int = 6, max_frequency: float = 32.0, index_dim: int = 64,
                 dropout: float = 0.0):
        super().__init__()
        self.num_bands, self.max_frequency, self.index_dim = num_bands, max_frequency, index_dim
        context_dim = point_token_dim(num_bands, index_dim)
        self.latents = nn.Parameter(torch.randn(num_latents, dim) * 0.02)
        self.layers = nn.ModuleList()
        for _ in range(depth):
            self.layers.append(nn.ModuleList([
                nn.LayerNorm(dim), nn.LayerNorm(context_dim),
                Attention(dim, context_dim, heads=cross_heads, dim_head=cross_dim_head, dropout=dropout),
                nn.LayerNorm(dim), FeedForward(dim, ff_mult, dropout),
                nn.ModuleList([nn.ModuleList([nn.LayerNorm(dim), Attention(dim, heads=heads, dim_head=dim_head,
                                                                           dropout=dropout),
                                              nn.LayerNorm(dim), FeedForward(dim, ff_mult, dropout)])
                               for _ in range(self_per_cross)]),
            ]))
        self.norm_out = nn.LayerNorm(dim)

    def forward(self, features: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        B, N, M, _ = features.shape
        tokens = point_tokens(features, self.num_bands, self.max_frequency, self.index_dim)
        key_mask = repeat(mask.bool(), "b n -> b (n m)", m=M)
        z = repeat(self.latents, "l d -> b l d", b=B)
        for norm_z, norm_ctx, cross, norm_ff, ff, self_layers in self.layers:
            z = z + cross(norm_z(z), norm_ctx(tokens), key_mask=key_mask)
            z = z + ff(norm_ff(z))
            for norm_a, attn, norm_f, ff_self in self_layers:
                z = z + attn(norm_a(z))
                z = z + ff_self(norm_f(z))
        return self.norm_out(z)
