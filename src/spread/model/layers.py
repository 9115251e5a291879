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


#: How an :class:`Attention` gets its keys and values.
KV_SOURCES = ("context", "self", "given")
#: Two ways to one cross-attention over a raw context (the perceiver's and the shape tokenizer's ``cross_mode``):
#: keys and values ``formed`` from it, or the queries carried into its channels (:meth:`Attention.absorbed`).
CROSS_MODES = ("formed", "absorbed")


class Attention(nn.Module):
    """Multi-head attention of queries x (B, Nq, dim) over a context (B, Nk, context_dim) (self if None).

    ``key_mask`` (B, Nk) bool marks the keys that may be attended to (True = real); ``key_bias`` (B, 1, 1, Nk) is
    the same as an additive float mask (0 or −inf), made once when several layers share the keys. Every query must
    have at least one real key. Output (B, Nq, dim).

    ``kv`` says where keys and values come from: ``context`` (``to_kv`` on the context), ``self`` (self-attention
    only: one ``to_qkv`` projection of x — one matrix product instead of two; checkpoints with separate
    ``to_q``/``to_kv`` load into it) or ``given`` (the caller passes the projected ``kv`` (B, Nk, 2·heads·dim_head),
    e.g. computed for several layers in one product).

    ``context_proj`` (a Linear shared by several layers, e.g. the shape-token projection) makes the keys and values
    ``to_kv(context_proj(context))``. Then neither is formed: each head's query is carried into the raw context's
    space instead (:meth:`absorbed`: ``q·(W_k P c) = (Pᵀ W_kᵀ q)·c``, the value product after the weighted sum), the
    same function, which for a narrow raw context and few queries (each object's one query per head over its 256
    shape tokens of 64 channels, vs keys and values of 2 × 512 channels per token, per block, per denoising step) is a
    small fraction of the work and memory.
    """

    def __init__(self, dim: int, context_dim: int | None = None, heads: int = 8, dim_head: int = 64,
                 dropout: float = 0.0, kv: str = "context"):
        super().__init__()
        if kv not in KV_SOURCES:
            raise ValueError(f"Attention: kv must be one of {KV_SOURCES}, got '{kv}'")
        inner = heads * dim_head
        self.heads, self.kv = heads, kv
        if kv == "self":
            self.to_qkv = nn.Linear(dim, 3 * inner, bias=False)
            self.register_load_state_dict_pre_hook(_fuse_legacy_qkv)
        else:
            self.to_q = nn.Linear(dim, inner, bias=False)
        if kv == "context":
            self.to_kv = nn.Linear(context_dim or dim, 2 * inner, bias=False)
        self.to_out = nn.Sequential(nn.Linear(inner, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, context: torch.Tensor | None = None, key_mask: torch.Tensor | None = None,
                context_proj: nn.Linear | None = None, kv: torch.Tensor | None = None,
                key_bias: torch.Tensor | None = None) -> torch.Tensor:
        if self.kv == "self":
            q, k, v = rearrange(self.to_qkv(x), "b n (three h d) -> three b h n d", three=3, h=self.heads)
        else:
            q = rearrange(self.to_q(x), "b n (h d) -> b h n d", h=self.heads)
            if self.kv == "context":
                context = x if context is None else context
                if context_proj is not None:
                    key_weight, value_weight = self.to_kv.weight.chunk(2, dim=0)  # (heads·dim_head, context_dim)
                    value_bias = None if context_proj.bias is None else value_weight @ context_proj.bias
                    return self.absorbed(q, context, key_weight @ context_proj.weight,
                                         value_weight @ context_proj.weight, value_bias,
                                         _mask(key_mask, key_bias, q.dtype))
                kv = self.to_kv(context)
            elif kv is None:
                raise ValueError("Attention(kv='given') needs kv=")
            k, v = rearrange(kv, "b n (two h d) -> two b h n d", two=2, h=self.heads)
        out = F.scaled_dot_product_attention(q, k, v, attn_mask=_mask(key_mask, key_bias, q.dtype))
        return self.to_out(rearrange(out, "b h n d -> b n (h d)"))

    def absorbed(self, q: torch.Tensor, context: torch.Tensor, key_weight: torch.Tensor, value_weight: torch.Tensor,
                 value_bias: torch.Tensor | None, mask: torch.Tensor | None) -> torch.Tensor:
        """Attention of queries q (B, heads, Nq, dim_head) over the keys ``key_weight·c (+ a key bias)`` and values
        ``value_weight·c + value_bias`` of a raw context c (B, Nk, raw) without forming them (key_weight,
        value_weight (heads·dim_head, raw); value_bias (heads·dim_head,) or None): with A_h, V_h head h's rows of
        the two weights, its logits are ``(q_h·A_h)·c_j`` (a key bias shifts a query's logits alike: softmax ignores
        it) and its output ``V_h·(Σ_j a_j c_j) + value_bias_h``. The heads share c, so they attend as B × (heads·Nq)
        queries of one head. Output ``to_out`` of it, (B, Nq, dim)."""
        B, heads, Nq, dim_head = q.shape
        raw = context.shape[-1]  # (explicit sizes throughout: B may be a data-dependent size under torch.compile)
        to_raw, from_raw = key_weight.view(heads, dim_head, raw), value_weight.view(heads, dim_head, raw)
        q_raw = torch.einsum("bhnd,hdr->bhnr", q, to_raw.to(q.dtype)).reshape(B, 1, heads * Nq, raw)
        c = context[:, None].to(q_raw.dtype)
        if queries_only(q_raw, c, mask):
            mixed = attend_queries_only(q_raw, c, mask, dim_head ** -0.5)
        else:
            mixed = F.scaled_dot_product_attention(q_raw, c, c, attn_mask=mask, scale=dim_head ** -0.5)
        out = torch.einsum("bhnr,hdr->bnhd", mixed.reshape(B, heads, Nq, raw), from_raw.to(mixed.dtype))
        if value_bias is not None:
            out = out + value_bias.view(heads, dim_head).to(out.dtype)
        return self.to_out(out.reshape(B, Nq, heads * dim_head))

    def attend_raw(self, x: torch.Tensor, context: torch.Tensor, key_weight: torch.Tensor, value_weight: torch.Tensor,
                   value_bias: torch.Tensor | None = None, key_bias: torch.Tensor | None = None) -> torch.Tensor:
        """Queries x (B, Nq, dim) attending to keys/values given as weights on a raw context (:meth:`absorbed`);
        ``key_bias`` (B, 1, 1, Nk) the additive mask. Output (B, Nq, dim)."""
        q = rearrange(self.to_q(x), "b n (h d) -> b h n d", h=self.heads)
        return self.absorbed(q, context, key_weight, value_weight, value_bias, _mask(None, key_bias, q.dtype))


#: The largest attention matrix (elements: batch × queries × keys) :func:`attend_queries_only` keeps for its backward.
QUERIES_ONLY_SCORES = 1 << 24


def queries_only(q: torch.Tensor, context: torch.Tensor, mask: torch.Tensor | None) -> bool:
    """Whether :func:`attend_queries_only` should replace ``F.scaled_dot_product_attention`` for queries q
    (B, 1, Nq, C) over a context (B, 1, Nk, C) used as both keys and values: on the CPU, in a step that will take
    gradients of the queries but not of the context (the perceiver's normalised point tokens, precomputed shape
    tokens), in float32 or float64, with an attention matrix of at most :data:`QUERIES_ONLY_SCORES` elements. There
    PyTorch's CPU flash attention still computes the context's two gradients in its backward; at the tiny config's
    perceiver the queries-only form is 1.8× faster forward + backward, at the paper's 1.4× (but its 4 × 256 × 40,000
    matrix is over the limit).
    Without gradients the flash kernel is 2× faster and is kept (``benchmarks/RESULTS.md``, stop 58)."""
    return (q.device.type == "cpu" and q.dtype in (torch.float32, torch.float64)  # bf16: flash keeps float32 sums
            and torch.is_grad_enabled() and q.requires_grad and not context.requires_grad
            and (mask is None or not mask.requires_grad)
            and q.shape[0] * q.shape[1] * q.shape[2] * context.shape[2] <= QUERIES_ONLY_SCORES)


def attend_queries_only(q: torch.Tensor, context: torch.Tensor, mask: torch.Tensor | None,
                        scale: float) -> torch.Tensor:
    """``softmax(q·cᵀ·scale + mask)·c`` for q (B, 1, Nq, C) and c (B, 1, Nk, C) (keys = values = c) by two matrix
    products and a softmax (the same function as ``F.scaled_dot_product_attention(q, c, c, mask, scale=scale)``);
    ``mask`` (B, 1, 1, Nk): bool (True = real key) or additive float."""
    logits = torch.matmul(q, context.transpose(-1, -2)) * scale
    if mask is not None:
        logits = logits.masked_fill(~mask, float("-inf")) if mask.dtype == torch.bool else logits + mask
    return torch.matmul(logits.softmax(-1), context)


def _mask(key_mask: torch.Tensor | None, key_bias: torch.Tensor | None, dtype: torch.dtype) -> torch.Tensor | None:
    """The attention mask of :class:`Attention`: ``key_bias`` (B, 1, 1, Nk) as given, else ``key_mask`` (B, Nk) as
    (B, 1, 1, Nk) bool; a float mask in the queries' dtype."""
    mask = key_bias
    if mask is None and key_mask is not None:
        mask = rearrange(key_mask, "b k -> b 1 1 k")
    if mask is not None and mask.is_floating_point() and mask.dtype != dtype:
        mask = mask.to(dtype)
    return mask


def round_up(n: int, multiple: int) -> int:
    """``n`` rounded up to a multiple of ``multiple`` (a token's padded channels, a batch's bucket of objects)."""
    return -(-int(n) // int(multiple)) * int(multiple)


def key_bias(key_mask: torch.Tensor) -> torch.Tensor:
    """(B, Nk) bool real keys → the additive mask (B, 1, 1, Nk) float32: 0 for real keys, −inf for the rest."""
    zero = torch.zeros((), device=key_mask.device)
    return torch.where(key_mask, zero, float("-inf"))[:, None, None, :]


def _fuse_legacy_qkv(module, state_dict, prefix, *args) -> None:
    """Load hook of a self-attention: a checkpoint's separate ``to_q`` and ``to_kv`` weights become ``to_qkv``."""
    q, kv = f"{prefix}to_q.weight", f"{prefix}to_kv.weight"
    if q in state_dict and kv in state_dict and f"{prefix}to_qkv.weight" not in state_dict:
        state_dict[f"{prefix}to_qkv.weight"] = torch.cat([state_dict.pop(q), state_dict.pop(kv)], 0)
