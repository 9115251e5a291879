"""Building blocks shared by the denoiser, the geometry perceiver and the shape tokenizer.

* :class:`AdaLayerNorm` — LayerNorm without affine parameters, scaled and shifted by a projection of
  the timestep embedding (FiLM / DiT's adaLN): ``LN(x)·(1 + γ(t)) + β(t)``.
* :class:`FeedForward` — GEGLU MLP (as the reference), ``dim → mult·dim → dim``.
* :class:`Attention` — multi-head (cross or self) attention on ``F.scaled_dot_product_attention``
  with an optional key-padding mask; keys masked out never influence any output.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn


class AdaLayerNorm(nn.Module):
    """LayerNorm conditioned on an embedding c: (..., dim), c (B, cond_dim) → (..., dim).

    ``c`` is broadcast over every dimension of ``x`` between the batch and the channels. The
    modulation starts at zero (identity LayerNorm) so a fresh block behaves like a plain pre-norm one.
    """

    def __init__(self, dim: int, cond_dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim, elementwise_affine=False)
        self.to_scale_shift = nn.Sequential(nn.SiLU(), nn.Linear(cond_dim, 2 * dim))
        nn.init.zeros_(self.to_scale_shift[1].weight)
        nn.init.zeros_(self.to_scale_shift[1].bias)

    def forward(self, x: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
        scale, shift = self.to_scale_shift(c).chunk(2, dim=-1)
        shape = (c.shape[0],) + (1,) * (x.dim() - 2) + (x.shape[-1],)
        return self.norm(x) * (1 + scale.view(shape)) + shift.view(shape)


class FeedForward(nn.Module):
    """GEGLU feed-forward (Shazeer 2020): Linear(dim → 2·h) → a·GELU(b) → Dropout → Linear(h → dim)."""

    def __init__(self, dim: int, mult: int = 4, dropout: float = 0.0):
        super().__init__()
        hidden = dim * mult
        self.proj_in = nn.Linear(dim, 2 * hidden)
        self.proj_out = nn.Sequential(nn.Dropout(dropout), nn.Linear(hidden, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, gate = self.proj_in(x).chunk(2, dim=-1)
        return self.proj_out(a * F.gelu(gate))


class Attention(nn.Module):
    """Multi-head attention of queries x (B, Nq, dim) over a context (B, Nk, context_dim) (self if None).

    ``key_mask`` (B, Nk) bool marks the keys that may be attended to (True = real). Every query must
    have at least one real key. Output (B, Nq, dim).

    ``context_proj`` (a Linear shared by several layers, e.g. the shape-token projection) makes the
    keys and values ``to_kv(context_proj(context))``; it is computed as one Linear with the composed
    weights, which is the same function but much cheaper when the raw context is narrower than
    ``context_dim`` (256 shape tokens of 64 channels per object vs 512).
    """

    def __init__(self, dim: int, context_dim: int | None = None, heads: int = 8, dim_head: int = 64,
                 dropout: float = 0.0):
        super().__init__()
        inner = heads * dim_head
        self.heads = heads
        self.to_q = nn.Linear(dim, inner, bias=False)
        self.to_kv = nn.Linear(context_dim or dim, 2 * inner, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None, key_mask: torch.Tensor | None = None,
                context_proj: nn.Linear | None = None) -> torch.Tensor:
        context = x if context is None else context
        q = rearrange(self.to_q(x), "b n (h d) -> b h n d", h=self.heads)
        if context_proj is None:
            kv = self.to_kv(context)
        else:
            weight = self.to_kv.weight @ context_proj.weight
            bias = None if context_proj.bias is None else self.to_kv.weight @ context_proj.bias
            kv = F.linear(context, weight, bias)
        k, v = rearrange(kv, "b n (two h d) -> two b h n d", two=2, h=self.heads)
        mask = None if key_mask is None else rearrange(key_mask, "b k -> b 1 1 k")
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)
        return self.to_out(rearrange(out, "b h n d -> b n (h d)"))
