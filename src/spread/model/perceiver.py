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

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from einops import rearrange, repeat
from torch import nn

from spread.model.encodings import fourier_dim, fourier_features, sinusoidal_embedding
from spread.model.layers import CROSS_MODES, Attention, FeedForward, key_bias, round_up

#: Length scales (metres) of the squashed signed-distance channels.
DISTANCE_SCALES = (0.01, 0.05, 0.25)
#: The point tokens carry trailing zero channels up to a multiple of this. On CUDA a bf16 matrix product whose inner
#: dimension is not a multiple of 8 runs in a slow kernel, and PyTorch's LayerNorm of rows of such a width in its
#: non-vectorised one (H200, one +Geometry training step at batch 16 × 20 × 2,000: 3.2 ms for the 107-channel
#: LayerNorm, 1.1 ms for the product; ``benchmarks/RESULTS.md``, stop 56). The padding meets zero weights. On the
#: CPU the tokens are not padded (:func:`token_multiple`): there PyTorch's fused LayerNorm of the unpadded rows is
#: 3.5–4.5× faster than the padded path's ``var_mean`` + ``addcmul``.
CHANNEL_MULTIPLE = 8


def token_multiple(device: torch.device) -> int:
    """The multiple a point token's channels are padded to on ``device``: :data:`CHANNEL_MULTIPLE` on CUDA, 1 (no
    padding) elsewhere."""
    return CHANNEL_MULTIPLE if torch.device(device).type == "cuda" else 1


def cross_mode(device: torch.device) -> str:
    """How the cross-attentions over the point tokens are computed on ``device`` (the same function either way,
    :class:`GeometryPerceiver`): ``absorbed`` on the CPU (measured there: the perceiver's forward + backward 1.24×
    faster at batch 4 × 20 × 2,000, 1.10–1.32× at the tiny config's sizes; ``benchmarks/RESULTS.md``, stop 57),
    ``formed`` on CUDA, where the absorbed form trades the keys/values tensor for 1.75× the attention arithmetic and
    is not yet timed (``bench_gpu.py --variants geometry:absorbed``)."""
    return "formed" if torch.device(device).type == "cuda" else "absorbed"


@dataclass
class StaticTokens:
    """The pose-independent channels of the point tokens, made once per sample: ``xyz`` (B, N·M, F) Fourier
    features of the canonical points, ``index`` (B, N·M, E + P) the object-index code followed by the P zero channels
    that pad a token to a multiple of :func:`token_multiple` (none on the CPU), ``key_bias`` (B, 1, 1, N·M) the
    additive attention mask of the points (0 for real objects' points, −inf for padding)."""

    xyz: torch.Tensor
    index: torch.Tensor
    key_bias: torch.Tensor


def static_tokens(points: torch.Tensor, mask: torch.Tensor, num_bands: int, max_frequency: float,
                  index_dim: int, multiple: int | None = None) -> StaticTokens:
    """:class:`StaticTokens` of canonical points (B, N, M, 3) (zero at padding objects) and ``mask`` (B, N); the
    tokens padded to a multiple of ``multiple`` channels (None: :func:`token_multiple` of the points' device)."""
    B, N, M, _ = points.shape
    channels = point_token_dim(num_bands, index_dim)
    multiple = token_multiple(points.device) if multiple is None else multiple
    index = sinusoidal_embedding(torch.arange(N, device=points.device), index_dim)  # (N, E)
    index = F.pad(index, (0, round_up(channels, multiple) - channels))  # (N, E + P), the padding last in the token
    return StaticTokens(rearrange(fourier_features(points, num_bands, max_frequency), "b n m c -> b (n m) c"),
                        repeat(index, "n e -> b (n m) e", b=B, m=M),
                        key_bias(repeat(mask.bool(), "b n -> b (n m)", m=M)))


def point_tokens(distance: torch.Tensor, static: StaticTokens, scales: torch.Tensor | None = None) -> torch.Tensor:
    """Signed distances (B, N, M) and the sample's :class:`StaticTokens` → (B, N·M, C + P)
    tokens [Fourier(xyz), d, tanh(d / s) for s in DISTANCE_SCALES, index code, P zeros] (module docstring; the zeros
    pad to the multiple the static tokens were made for, :func:`token_multiple`); ``scales``: the DISTANCE_SCALES
    as a tensor on the device (made here when not given)."""
    d = rearrange(distance, "b n m -> b (n m) 1")
    if scales is None:
        scales = torch.tensor(DISTANCE_SCALES, device=d.device)
    scales = scales.to(d.dtype)
    return torch.cat([static.xyz.to(d.dtype), d, torch.tanh(d / scales), static.index.to(d.dtype)], dim=-1)


#: Channels of :func:`object_summary`.
SUMMARY_DIM = 2 + len(DISTANCE_SCALES) + 2 + 3 + 3
#: Length scale (metres) of the contact weight in :func:`object_summary`.
CONTACT_SCALE = 0.02


def object_summary(distance: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Each object's own geometric state, for its node (``geometry_summary``): signed distances (B, N, M) metres of
    its canonical points (B, N, M, 3) → (B, N, SUMMARY_DIM): its deepest point's d (clipped to [−0.25, 0.25] m) and
    tanh(d_min / s) for s in DISTANCE_SCALES, d_min < 0 as 0/1, the share of its points inside (d < 0) and within
    1 cm, the depth-weighted mean canonical position of its points inside (where it penetrates: which way is out),
    and the contact-weighted mean canonical position (weight exp(−max(d, 0) / CONTACT_SCALE): where it touches)."""
    d = distance
    d_min = d.amin(-1, keepdim=True)
    inside = (d < 0).to(d.dtype)
    depth = torch.relu(-d)[..., None]
    where_in = (depth * points).sum(-2) / depth.sum(-2).clamp_min(1e-6)
    contact = torch.exp(-torch.relu(d) / CONTACT_SCALE)[..., None]
    where_touch = (contact * points).sum(-2) / contact.sum(-2).clamp_min(1e-6)
    scales = torch.tensor(DISTANCE_SCALES, device=d.device, dtype=d.dtype)
    return torch.cat([d_min.clamp(-0.25, 0.25), (d_min < 0).to(d.dtype), torch.tanh(d_min / scales),
                      inside.mean(-1, keepdim=True), (d < 0.01).to(d.dtype).mean(-1, keepdim=True),
                      where_in, where_touch], dim=-1)


#: Channels of :func:`pair_features`: for each direction of a pair, d clipped, d < 0, tanh(d / s).
PAIR_DIM = 2 * (2 + len(DISTANCE_SCALES))


def pair_features(pair: torch.Tensor) -> torch.Tensor:
    """Each ordered pair's geometric state, for its edge (``geometry_pairs``): pair distances (B, N, N) metres (i's
    deepest point with respect to j alone: :func:`spread.model.parts_distance.parts_distances`) → (B, N, N,
    PAIR_DIM): for d_ij and then d_ji, d clipped to [−0.25, 0.25] m, d < 0 as 0/1, and tanh(d / s) for s in
    DISTANCE_SCALES — so the edge of a laptop 3 cm deep in the bed it stands on reads it, in both directions."""
    scales = torch.tensor(DISTANCE_SCALES, device=pair.device, dtype=pair.dtype)
    both = torch.stack([pair, pair.transpose(1, 2)], dim=-1)[..., None]  # (B, N, N, 2, 1)
    feats = torch.cat([both.clamp(-0.25, 0.25), (both < 0).to(pair.dtype), torch.tanh(both / scales)], dim=-1)
    return feats.flatten(-2)


def point_token_dim(num_bands: int, index_dim: int) -> int:
    """Channels of a point token (its zero padding not counted: what the LayerNorm normalises over)."""
    return fourier_dim(3, num_bands) + 1 + len(DISTANCE_SCALES) + index_dim


class GeometryPerceiver(nn.Module):
    """Signed distances (B, N, M) + the sample's :class:`StaticTokens` → scene geometry tokens (B, num_latents, dim).

    The point tokens are the largest tensor of the step (B·N·M tokens): each cross-attention's pre-LayerNorm and
    key/value projection of them are computed for all ``depth`` cross-attentions at once — one normalisation
    (the LayerNorm without its affine part) and one matrix product whose weights fold in each layer's LayerNorm
    scale and shift (``context_scale``, ``context_shift`` (depth, C), ``context_kv`` (depth, 2·heads·dim_head, C)):
    ``to_kv(LN(x)·w + b) = (W·diag(w))·LN(x) + W·b``, the same function. Checkpoints with one LayerNorm and
    ``to_kv`` per layer load into it. Padded tokens (CUDA: :func:`token_multiple`): the normalisation's mean and
    variance are those of a token's C real channels, its zero padding is normalised too and met by zero columns of
    the product's weight.

    Two ways to the same function (:func:`cross_mode`, by device): ``formed`` makes those keys and values
    (B, N·M, depth·2·heads·dim_head); ``absorbed`` never does — each cross-attention carries its queries into the
    normalised tokens' space and attends over the tokens themselves (:meth:`spread.model.layers.Attention.absorbed`:
    the layer's key and value weights with its LayerNorm scale folded in; its shift's key part dropped, as softmax
    ignores it, its value part added after)."""

    def __init__(self, dim: int, num_latents: int = 256, depth: int = 4, self_per_cross: int = 2,
                 cross_heads: int = 1, cross_dim_head: int = 64, heads: int = 8, dim_head: int = 64,
                 ff_mult: int = 4, num_bands: int = 6, max_frequency: float = 32.0, index_dim: int = 64,
                 dropout: float = 0.0):
        super().__init__()
        self.num_bands, self.max_frequency, self.index_dim = num_bands, max_frequency, index_dim
        context_dim = point_token_dim(num_bands, index_dim)
        self.latents = nn.Parameter(torch.randn(num_latents, dim) * 0.02)
        self.context_norm = nn.LayerNorm(context_dim, elementwise_affine=False)
        self.context_scale = nn.Parameter(torch.ones(depth, context_dim))
        self.context_shift = nn.Parameter(torch.zeros(depth, context_dim))
        self.context_kv = nn.Parameter(torch.empty(depth, 2 * cross_heads * cross_dim_head, context_dim))
        for weight in self.context_kv.data:  # each layer's as nn.Linear initialises its weight
            nn.init.kaiming_uniform_(weight, a=math.sqrt(5))
        self.layers = nn.ModuleList()
        for _ in range(depth):
            self.layers.append(nn.ModuleList([
                nn.LayerNorm(dim),
                Attention(dim, heads=cross_heads, dim_head=cross_dim_head, dropout=dropout, kv="given"),
                nn.LayerNorm(dim), FeedForward(dim, ff_mult, dropout),
                nn.ModuleList([nn.ModuleList([nn.LayerNorm(dim), Attention(dim, heads=heads, dim_head=dim_head,
                                                                           dropout=dropout, kv="self"),
                                              nn.LayerNorm(dim), FeedForward(dim, ff_mult, dropout)])
                               for _ in range(self_per_cross)]),
            ]))
        self.norm_out = nn.LayerNorm(dim)
        self.register_buffer("distance_scales", torch.tensor(DISTANCE_SCALES), persistent=False)
        self.register_load_state_dict_pre_hook(_legacy_layout)

    def static(self, points: torch.Tensor, mask: torch.Tensor) -> StaticTokens:
        """The sample's :class:`StaticTokens` (canonical points (B, N, M, 3), zero at padding; mask (B, N))."""
        return static_tokens(points, mask, self.num_bands, self.max_frequency, self.index_dim)

    def normalise(self, tokens: torch.Tensor) -> torch.Tensor:
        """Point tokens (B, K, C + P) — C channels, then P zeros (:func:`point_tokens`) — LayerNormed over their C
        real channels without the affine part (biased variance, as nn.LayerNorm), all C + P of them (B, K, C + P)."""
        channels = self.context_kv.shape[-1]
        if tokens.shape[-1] == channels:  # unpadded (the CPU)
            return self.context_norm(tokens)
        var, mean = torch.var_mean(tokens[..., :channels], dim=-1, correction=0, keepdim=True)
        rstd = torch.rsqrt(var + self.context_norm.eps)
        return torch.addcmul(-mean * rstd, tokens, rstd)  # (x − μ)/σ

    def layer_weights(self, width: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Each cross-attention's key/value weight on the normalised tokens (depth, 2·heads·dim_head, ``width``: its
        LayerNorm scale folded in, zero columns for the padding) and bias (depth, 2·heads·dim_head)."""
        weight = self.context_kv * self.context_scale[:, None, :]
        bias = torch.einsum("lkc,lc->lk", self.context_kv, self.context_shift)
        return F.pad(weight, (0, width - weight.shape[-1])), bias

    def context(self, tokens: torch.Tensor) -> torch.Tensor:
        """Keys and values (B, K, depth·2·heads·dim_head) of every cross-attention for point tokens (B, K, C + P):
        C channels, then P zeros (:func:`point_tokens`)."""
        weight, bias = self.layer_weights(tokens.shape[-1])
        normed = self.normalise(tokens)
        return F.linear(normed, weight.flatten(0, 1).to(normed.dtype), bias.flatten().to(normed.dtype))

    def forward(self, distance: torch.Tensor, static: StaticTokens, mode: str | None = None) -> torch.Tensor:
        """Signed distances (B, N, M) (metres) of the sample's points → scene tokens (B, num_latents, dim);
        ``mode``: one of :data:`CROSS_MODES` (None: :func:`cross_mode` of the device)."""
        mode = cross_mode(distance.device) if mode is None else mode
        if mode not in CROSS_MODES:
            raise ValueError(f"GeometryPerceiver: mode must be one of {CROSS_MODES}, got {mode!r}")
        tokens = point_tokens(distance, static, self.distance_scales)
        if mode == "formed":
            kv = self.context(tokens).chunk(len(self.layers), dim=-1)
        else:
            normed = self.normalise(tokens)
            weight, bias = self.layer_weights(tokens.shape[-1])
            half = weight.shape[1] // 2
        z = repeat(self.latents, "l d -> b l d", b=distance.shape[0])
        for i, (norm_z, cross, norm_ff, ff, self_layers) in enumerate(self.layers):
            if mode == "formed":
                z = z + cross(norm_z(z), kv=kv[i], key_bias=static.key_bias)
            else:
                z = z + cross.attend_raw(norm_z(z), normed, weight[i, :half], weight[i, half:], bias[i, half:],
                                         key_bias=static.key_bias)
            z = z + ff(norm_ff(z))
            for norm_a, attn, norm_f, ff_self in self_layers:
                z = z + attn(norm_a(z))
                z = z + ff_self(norm_f(z))
        return self.norm_out(z)


def _legacy_layout(module, state_dict, prefix, *args) -> None:
    """Load hook: a checkpoint of the layout with one context LayerNorm and ``to_kv`` per cross-attention
    (``layers.i.{0 norm_z, 1 norm_ctx, 2 cross, 3 norm_ff, 4 ff, 5 self}``) → the stacked context weights and
    ``layers.i.{0 norm_z, 1 cross, 2 norm_ff, 3 ff, 4 self}``."""
    if f"{prefix}context_kv" in state_dict or f"{prefix}layers.0.2.to_kv.weight" not in state_dict:
        return
    depth = len(module.layers)
    head = f"{prefix}layers."
    scale, shift, kv = [], [], []
    for i in range(depth):
        scale.append(state_dict.pop(f"{head}{i}.1.weight"))
        shift.append(state_dict.pop(f"{head}{i}.1.bias"))
        kv.append(state_dict.pop(f"{head}{i}.2.to_kv.weight"))
    for key in [k for k in state_dict if k.startswith(head)]:
        layer, part, rest = key[len(head):].split(".", 2)
        if part in ("2", "3", "4", "5"):
            state_dict[f"{head}{layer}.{int(part) - 1}.{rest}"] = state_dict.pop(key)
    state_dict[f"{prefix}context_scale"] = torch.stack(scale)
    state_dict[f"{prefix}context_shift"] = torch.stack(shift)
    state_dict[f"{prefix}context_kv"] = torch.stack(kv)
