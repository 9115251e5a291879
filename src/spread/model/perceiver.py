"""Geometry perceiver: signed chamfer point features of the whole scene → a few scene-level tokens.

Input: the signed distances (B, N, M) of :func:`spread.model.geometry.signed_distances` (metres) and the
sample's :class:`StaticTokens` (what does not change between denoising steps: the canonical points' Fourier
features, the object-index codes, the key mask; :meth:`GeometryPerceiver.static`, made once per sample). Output:
(B, num_latents, dim) tokens, shared by the scene (as the release: 256 latents for all objects), that every
object node attends to.

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

from dataclasses import dataclass

import torch
from einops import rearrange, repeat
from torch import nn

from spread.model.encodings import fourier_dim, fourier_features, sinusoidal_embedding
from spread.model.layers import Attention, FeedForward

#: Length scales (metres) of the squashed signed-distance channels.
DISTANCE_SCALES = (0.01, 0.05, 0.25)


@dataclass
class StaticTokens:
    """The pose-independent channels of the point tokens, made once per sample: ``xyz`` (B, N·M, F) Fourier
    features of the canonical points, ``index`` (B, N·M, E) the object-index code, ``key_mask`` (B, N·M) the
    points of real objects."""

    xyz: torch.Tensor
    index: torch.Tensor
    key_mask: torch.Tensor


def static_tokens(points: torch.Tensor, mask: torch.Tensor, num_bands: int, max_frequency: float,
                  index_dim: int) -> StaticTokens:
    """:class:`StaticTokens` of canonical points (B, N, M, 3) (zero at padding objects) and ``mask`` (B, N)."""
    B, N, M, _ = points.shape
    index = sinusoidal_embedding(torch.arange(N, device=points.device), index_dim)  # (N, E)
    return StaticTokens(rearrange(fourier_features(points, num_bands, max_frequency), "b n m c -> b (n m) c"),
                        repeat(index, "n e -> b (n m) e", b=B, m=M),
                        repeat(mask.bool(), "b n -> b (n m)", m=M))


def point_tokens(distance: torch.Tensor, static: StaticTokens, scales: torch.Tensor | None = None) -> torch.Tensor:
    """Signed distances (B, N, M) and the sample's :class:`StaticTokens` → (B, N·M, point_token_dim(...)) tokens
    [Fourier(xyz), d, tanh(d / s) for s in DISTANCE_SCALES, index code] (module docstring); ``scales``: the
    DISTANCE_SCALES as a tensor on the device (made here when not given)."""
    d = rearrange(distance, "b n m -> b (n m) 1")
    if scales is None:
        scales = torch.tensor(DISTANCE_SCALES, device=d.device)
    scales = scales.to(d.dtype)
    return torch.cat([static.xyz.to(d.dtype), d, torch.tanh(d / scales), static.index.to(d.dtype)], dim=-1)


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
        self.register_buffer("distance_scales", torch.tensor(DISTANCE_SCALES), persistent=False)

    def static(self, points: torch.Tensor, mask: torch.Tensor) -> StaticTokens:
        """The sample's :class:`StaticTokens` (canonical points (B, N, M, 3), zero at padding; mask (B, N))."""
        return static_tokens(points, mask, self.num_bands, self.max_frequency, self.index_dim)

    def forward(self, distance: torch.Tensor, static: StaticTokens) -> torch.Tensor:
        """Signed distances (B, N, M) (metres) of the sample's points → scene tokens (B, num_latents, dim)."""
        tokens = point_tokens(distance, static, self.distance_scales)
        z = repeat(self.latents, "l d -> b l d", b=distance.shape[0])
        for norm_z, norm_ctx, cross, norm_ff, ff, self_layers in self.layers:
            z = z + cross(norm_z(z), norm_ctx(tokens), key_mask=static.key_mask)
            z = z + ff(norm_ff(z))
            for norm_a, attn, norm_f, ff_self in self_layers:
                z = z + attn(norm_a(z))
                z = z + ff_self(norm_f(z))
        return self.norm_out(z)
