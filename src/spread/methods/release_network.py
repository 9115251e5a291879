"""The SPREAD release's denoising network, parameter for parameter, so the authors' ``ckpt.pth`` loads into it.

Our own implementation of the network documented in reference_implementation.md §2 (``Sg2ScTransformer
DiffusionWrapper``): the module and parameter names follow the release's state-dict layout, so its weights
load with no missing or unexpected keys (:func:`load_release_checkpoint`). Checked against the release's own
code (run outside this repository at reduced sizes; tests/data/release_network_fixture.npz holds its random
weights, inputs and outputs; tests/test_release_checkpoint.py).

Inputs (B objects-batch, N entries **including the release's placeholder at index 0**):

* ``box`` (B, N, 12): normalised [translation 3, size 3, rot6d 6] (release §1.4–1.5);
* ``pc_feat`` (B, N, P, 4): [local xyz, signed chamfer distance] per point (§2.2; zeros at index 0);
* ``miche_feat`` (B, N, L, 64): Michelangelo shape latents (L = 256 in the release);
* ``edges`` (B, N, N) long: physical codes 0 Empty, 1 Support, 2 Contact, 3 none/padding;
* ``regions`` (B, N, N) long: spatial codes 0..6 (our DESIGN §3 order), 7 padding;
* ``t`` (B,) or scalar: the training timestep; ``mask`` (B, N) float, 1 for real entries (index 0 included);
* ``condition`` (B or 1, K, context_dim): the unused image tokens; None = zeros, as the release feeds them.

Output: ε̂ (B, N, 12), zero where ``mask`` is 0. Everything runs in eval mode here (dropout off); the
release's classifier-free graph dropout is a training detail and is not reproduced.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn

from spread.model.encodings import sinusoidal_embedding

#: The release's ``_orig_mod.`` (torch.compile) and ``network.`` (the wrapper inside the diffusion module) prefixes.
COMPILED_PREFIX = "_orig_mod."
NETWORK_PREFIX = "network."


@dataclass
class ReleaseNetworkConfig:
    """Sizes of the release's network; defaults are the release's (reference §2.1, §2.3)."""

    attn_dim: int = 512
    t_dim: int = 128
    n_heads: int = 8
    n_layers: int = 6
    context_dim: int = 768
    region_vocab: int = 8  # 7 region codes + padding
    edge_vocab: int = 4  # 3 predicates + none
    dropout: float = 0.1
    index_dim: int = 128  # sinusoidal code of the entry index (fixed in the release)
    index_max: int = 100
    miche_dim: int = 64
    box_dim: int = 12
    # perceiver
    point_channels: int = 4
    num_freq_bands: int = 64
    max_freq: float = 1120.0
    perceiver_depth: int = 4
    num_latents: int = 256
    cross_heads: int = 1
    cross_dim_head: int = 64
    latent_heads: int = 8
    latent_dim_head: int = 64
    self_per_cross: int = 2
    num_classes: int = 1000  # the perceiver's unused classifier head (its weights are in the checkpoint)
    max_objects: int = 12  # the release's max_length (data side)

    def to_dict(self) -> dict:
        return asdict(self)


# ---- layers (release semantics) ------------------------------------------------------------------

def _heads(x: torch.Tensor, h: int) -> torch.Tensor:
    """(B, n, h·d) → (B, h, n, d)."""
    B, n, hd = x.shape
    return x.view(B, n, h, hd // h).transpose(1, 2)


def _merge(x: torch.Tensor) -> torch.Tensor:
    """(B, h, n, d) → (B, n, h·d)."""
    B, h, n, d = x.shape
    return x.transpose(1, 2).reshape(B, n, h * d)


class MaskedAttention(nn.Module):
    """q/k/v without bias, Linear + dropout out; queries and outputs zeroed by ``mask`` (B, Nq); the context is
    broadcast over the batch when it has one entry."""

    def __init__(self, query_dim: int, context_dim: int | None, heads: int, hidden: int, dropout: float):
        super().__init__()
        context_dim = context_dim or query_dim
        self.heads = heads
        self.to_q = nn.Linear(query_dim, hidden, bias=False)
        self.to_k = nn.Linear(context_dim, hidden, bias=False)
        self.to_v = nn.Linear(context_dim, hidden, bias=False)
        self.to_out = nn.Sequential(nn.Linear(hidden, query_dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, context: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
        q = self.to_q(x)
        if mask is not None:
            q = q * mask[..., None]
        if context.shape[0] != x.shape[0]:
            context = context.expand(x.shape[0], *context.shape[1:])
        out = F.scaled_dot_product_attention(_heads(q, self.heads), _heads(self.to_k(context), self.heads),
                                             _heads(self.to_v(context), self.heads))
        out = self.to_out(_merge(out))
        return out if mask is None else out * mask[..., None]


class ChannelGraphAttention(nn.Module):
    """InstructScene's graph attention: per-channel scores q_i ⊙ k_j / √d modulated by the edge,
    ``s ← (1 + W_mul e) ⊙ s + W_add e``; the edge update is ``W_e_out s``; softmax over j per channel."""

    def __init__(self, dim: int, edge_dim: int, heads: int, hidden: int, dropout: float):
        super().__init__()
        self.heads, self.scale = heads, (hidden // heads) ** -0.5
        self.to_q = nn.Linear(dim, hidden, bias=False)
        self.to_k = nn.Linear(dim, hidden, bias=False)
        self.to_v = nn.Linear(dim, hidden, bias=False)
        self.to_out = nn.Sequential(nn.Linear(hidden, dim), nn.Dropout(dropout))
        self.to_e_mul = nn.Linear(edge_dim, hidden, bias=False)
        self.to_e_add = nn.Linear(edge_dim, hidden, bias=False)
        self.to_e_out = nn.Sequential(nn.Linear(hidden, edge_dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, e: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        B, N, _ = x.shape
        h = self.heads
        xm = mask[..., None]  # (B, N, 1)
        pair = mask[:, :, None, None] * mask[:, None, :, None]  # (B, N, N, 1)
        q, k, v = (_heads(f(x) * xm, h) for f in (self.to_q, self.to_k, self.to_v))  # (B, h, N, d)
        s = q[:, :, :, None] * k[:, :, None] * self.scale  # (B, h, N, N, d)

        def split(t):  # (B, N, N, h·d) → (B, h, N, N, d)
            return t.view(B, N, N, h, -1).permute(0, 3, 1, 2, 4)

        s = (1.0 + split(self.to_e_mul(e) * pair)) * s + split(self.to_e_add(e) * pair)
        e_out = self.to_e_out(s.permute(0, 2, 3, 1, 4).reshape(B, N, N, -1)) * pair
        keys = mask[:, None, None, :, None].bool()  # key j real
        a = s.masked_fill(~keys, float("-inf")).softmax(dim=3)
        out = (a * v[:, :, None]).sum(dim=3)  # (B, h, N, d)
        return self.to_out(_merge(out)) * xm, e_out


class GEGLU(nn.Module):
    def __init__(self, dim_in: int, dim_out: int):
        super().__init__()
        self.proj = nn.Linear(dim_in, 2 * dim_out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        a, gate = self.proj(x).chunk(2, dim=-1)
        return a * F.gelu(gate)


class GatedFeedForward(nn.Module):
    def __init__(self, dim: int, dropout: float, mult: int = 4):
        super().__init__()
        self.mlp = nn.Sequential(GEGLU(dim, mult * dim), nn.Dropout(dropout), nn.Linear(mult * dim, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.mlp(x)


class TimeAdaLN(nn.Module):
    """``LN(x)·(1 + scale) + shift`` with [scale, shift] = Linear(GELU(t_emb)) (scale first)."""

    def __init__(self, dim: int, t_dim: int):
        super().__init__()
        self.linear = nn.Linear(t_dim, 2 * dim)
        self.dim = dim

    def forward(self, x: torch.Tensor, t_emb: torch.Tensor) -> torch.Tensor:
        emb = self.linear(F.gelu(t_emb))
        emb = emb.view(emb.shape[0], *([1] * (x.dim() - 2)), emb.shape[-1])
        scale, shift = emb.chunk(2, dim=-1)
        return F.layer_norm(x, (self.dim,)) * (1.0 + scale) + shift


class GraphLayer(nn.Module):
    """AdaLN graph attention (nodes and edges), AdaLN cross-attention to the condition, AdaLN gated FFs."""

    def __init__(self, c: ReleaseNetworkConfig):
        super().__init__()
        d, ed = c.attn_dim, c.attn_dim // 4
        self.graph_attn = ChannelGraphAttention(d, ed, c.n_heads, d, c.dropout)
        self.ff_x = GatedFeedForward(d, c.dropout)
        self.ff_e = GatedFeedForward(ed, c.dropout)
        self.ga_x_norm, self.ff_x_norm = TimeAdaLN(d, c.t_dim), TimeAdaLN(d, c.t_dim)
        self.ga_e_norm, self.ff_e_norm = TimeAdaLN(ed, c.t_dim), TimeAdaLN(ed, c.t_dim)
        self.cross_attn = MaskedAttention(d, c.context_dim, c.n_heads, d, c.dropout)
        self.ca_norm = TimeAdaLN(d, c.t_dim)

    def forward(self, x, e, t_emb, context, mask):
        x_, e_ = self.graph_attn(self.ga_x_norm(x, t_emb), self.ga_e_norm(e, t_emb), mask)
        x, e = x + x_, e + e_
        x = x + self.cross_attn(self.ca_norm(x, t_emb), context, mask)
        x = x + self.ff_x(self.ff_x_norm(x, t_emb))
        return x, e + self.ff_e(self.ff_e_norm(e, t_emb))


class Block(nn.Module):
    """Box token ← its own shape tokens, ← the scene's geometry latents (post-LN), then the graph layer."""

    def __init__(self, c: ReleaseNetworkConfig):
        super().__init__()
        d = c.attn_dim
        self.box_to_miche = MaskedAttention(d, d, c.n_heads, d, c.dropout)
        self.norm1 = nn.LayerNorm(d)
        self.box_to_pc = MaskedAttention(d, d, c.n_heads, d, c.dropout)
        self.norm_pc = nn.LayerNorm(d)
        self.graph_layer = GraphLayer(c)

    def forward(self, box, miche, pc, e, t_emb, context, mask):
        B, N = mask.shape
        box = self.norm1(box + self.box_to_miche(box, miche)).view(B, N, -1)  # (B·N, 1, d) → (B, N, d)
        box = self.norm_pc(box + self.box_to_pc(box, pc))
        box, e = self.graph_layer(box, e, t_emb, context, mask)
        return box.reshape(B * N, 1, -1), e


# ---- the perceiver (release §2.3) ----------------------------------------------------------------

class PreNorm(nn.Module):
    def __init__(self, dim: int, fn: nn.Module, context_dim: int | None = None):
        super().__init__()
        self.fn, self.norm = fn, nn.LayerNorm(dim)
        self.norm_context = nn.LayerNorm(context_dim) if context_dim else None

    def forward(self, x, context=None):
        if self.norm_context is not None:
            return self.fn(self.norm(x), self.norm_context(context))
        return self.fn(self.norm(x))


class LatentAttention(nn.Module):
    def __init__(self, dim: int, context_dim: int | None, heads: int, dim_head: int):
        super().__init__()
        self.heads = heads
        self.to_q = nn.Linear(dim, heads * dim_head, bias=False)
        self.to_kv = nn.Linear(context_dim or dim, 2 * heads * dim_head, bias=False)
        self.to_out = nn.Linear(heads * dim_head, dim)

    def forward(self, x, context=None):
        k, v = self.to_kv(x if context is None else context).chunk(2, dim=-1)
        out = F.scaled_dot_product_attention(_heads(self.to_q(x), self.heads), _heads(k, self.heads),
                                             _heads(v, self.heads))
        return self.to_out(_merge(out))


class _GLU(nn.Module):
    def forward(self, x):
        a, gate = x.chunk(2, dim=-1)
        return a * F.gelu(gate)


class LatentFeedForward(nn.Module):
    def __init__(self, dim: int, mult: int = 4):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(dim, 2 * mult * dim), _GLU(), nn.Linear(mult * dim, dim), nn.Dropout(0.0))

    def forward(self, x):
        return self.net(x)


class PointPerceiver(nn.Module):
    """(B, N, P, 4) point features → (B, num_latents, attn_dim): each point token is its features, the
    sinusoidal code of its entry index and Fourier features of its point index (linspace(−1, 1, P))."""

    def __init__(self, c: ReleaseNetworkConfig):
        super().__init__()
        d = c.attn_dim
        self.c = c
        input_dim = c.point_channels + c.index_dim + 2 * c.num_freq_bands + 1
        self.latents = nn.Parameter(torch.randn(c.num_latents, d))
        self.layers = nn.ModuleList()
        for _ in range(c.perceiver_depth):
            self.layers.append(nn.ModuleList([
                PreNorm(d, LatentAttention(d, input_dim, c.cross_heads, c.cross_dim_head), context_dim=input_dim),
                PreNorm(d, LatentFeedForward(d)),
                nn.ModuleList([nn.ModuleList([PreNorm(d, LatentAttention(d, None, c.latent_heads, c.latent_dim_head)),
                                              PreNorm(d, LatentFeedForward(d))]) for _ in range(c.self_per_cross)]),
            ]))
        self.to_logits = nn.Sequential(nn.Identity(), nn.LayerNorm(d), nn.Linear(d, c.num_classes))  # unused head

    def point_codes(self, N: int, P: int, device, dtype) -> torch.Tensor:
        c = self.c
        index = sinusoidal_embedding(torch.arange(N, device=device), c.index_dim).to(dtype)  # (N, 128)
        pos = torch.linspace(-1.0, 1.0, P, device=device, dtype=dtype)[:, None]
        scales = torch.linspace(1.0, c.max_freq / 2, c.num_freq_bands, device=device, dtype=dtype)
        angles = pos * scales * math.pi
        fourier = torch.cat([angles.sin(), angles.cos(), pos], dim=-1)  # (P, 2·bands + 1)
        return torch.cat([index[:, None].expand(N, P, -1), fourier[None].expand(N, P, -1)], dim=-1)

    def forward(self, feats: torch.Tensor) -> torch.Tensor:
        B, N, P, _ = feats.shape
        codes = self.point_codes(N, P, feats.device, feats.dtype)
        tokens = torch.cat([feats, codes[None].expand(B, -1, -1, -1)], dim=-1).reshape(B, N * P, -1)
        z = self.latents[None].expand(B, -1, -1)
        for cross, cross_ff, self_layers in self.layers:
            z = z + cross(z, tokens)
            z = z + cross_ff(z)
            for attn, ff in self_layers:
                z = z + attn(z)
                z = z + ff(z)
        return z


# ---- the network ---------------------------------------------------------------------------------

class _TimeMLP(nn.Module):
    def __init__(self, t_dim: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(t_dim, t_dim), nn.GELU(), nn.Linear(t_dim, t_dim))

    def forward(self, x):
        return self.mlp(x)


def time_code(t: torch.Tensor, dim: int, max_period: float = 10_000.0) -> torch.Tensor:
    """The release's timestep code: [cos, sin] of t · exp(−ln(max_period) k / (dim/2)), k < dim/2."""
    half = dim // 2
    freqs = torch.exp(-math.log(max_period) * torch.arange(half, device=t.device).float() / half)
    angles = t.float()[:, None] * freqs[None]
    return torch.cat([angles.cos(), angles.sin()], dim=-1)


class ReleaseNetwork(nn.Module):
    """ε̂(box_t, t | point features, shape latents, graphs) of the release (module docstring)."""

    def __init__(self, config: ReleaseNetworkConfig | dict | None = None):
        super().__init__()
        c = config if isinstance(config, ReleaseNetworkConfig) else ReleaseNetworkConfig(**(config or {}))
        self.config = c
        d, q = c.attn_dim, c.attn_dim // 4
        self.miche_proj = nn.Linear(c.miche_dim, d)
        self.box_proj = nn.Linear(c.box_dim + c.index_dim, d)
        self.pc_preceiver = PointPerceiver(c)  # sic: the release's attribute name
        self.edge_embed = nn.Sequential(nn.Embedding(c.edge_vocab, q), nn.GELU(), nn.Linear(q, q))
        self.region_embed = nn.Sequential(nn.Embedding(c.region_vocab, q), nn.GELU(), nn.Linear(q, q))
        self.edge_proj_in = nn.Linear(2 * q, q)
        self.time_embed = nn.Sequential(nn.Identity(), _TimeMLP(c.t_dim))
        self.transformer_blocks = nn.ModuleList([Block(c) for _ in range(c.n_layers)])
        self.proj_out = nn.Sequential(nn.LayerNorm(d), nn.Linear(d, c.box_dim))

    def forward(self, box: torch.Tensor, pc_feat: torch.Tensor, miche_feat: torch.Tensor, edges: torch.Tensor,
                regions: torch.Tensor, t, condition: torch.Tensor | None = None,
                mask: torch.Tensor | None = None) -> torch.Tensor:
        c = self.config
        B, N = box.shape[:2]
        mask = torch.ones(B, N, device=box.device) if mask is None else mask.to(box.dtype)
        t = torch.as_tensor(t, device=box.device).reshape(-1).expand(B) if torch.as_tensor(t).numel() == 1 \
            else torch.as_tensor(t, device=box.device).reshape(B)
        index = sinusoidal_embedding(torch.arange(N, device=box.device), c.index_dim).to(box.dtype)
        box_emb = self.box_proj(torch.cat([box, index[None].expand(B, -1, -1)], dim=-1)).reshape(B * N, 1, -1)
        miche = self.miche_proj(miche_feat).reshape(B * N, miche_feat.shape[2], -1)
        pc = self.pc_preceiver(pc_feat)
        e = self.edge_proj_in(torch.cat([self.edge_embed(edges.long()), self.region_embed(regions.long())], dim=-1))
        t_emb = self.time_embed[1](time_code(t, c.t_dim))
        if condition is None:
            condition = torch.zeros(1, 1, c.context_dim, device=box.device, dtype=box.dtype)
        for block in self.transformer_blocks:
            box_emb, e = block(box_emb, miche, pc, e, t_emb, condition, mask)
        return self.proj_out(box_emb.view(B, N, -1)) * mask[..., None]


# ---- the checkpoint --------------------------------------------------------------------------------

class ReleaseCheckpointError(ValueError):
    """A ``ckpt.pth`` that does not fit the network (the message names the file and the keys)."""


def release_state_dict(ckpt: dict, source: str = "ckpt.pth", use_ema: bool = True) -> dict[str, torch.Tensor]:
    """The network's weights from a release checkpoint dict ``{model, optimizer, ema_states}``: ``_orig_mod.``
    stripped, the ``network.`` part of the diffusion module, the EMA shadow parameters (diffusers' EMAModel:
    one tensor per parameter of the whole module, in registration order = the order of ``model``'s keys) in
    place of the raw weights when ``use_ema``."""
    if not isinstance(ckpt, dict) or "model" not in ckpt:
        raise ReleaseCheckpointError(f"{source}: expected a dict with key 'model' (the release's "
                                     f"{{model, optimizer, ema_states}}), got {type(ckpt).__name__}"
                                     + (f" with keys {sorted(ckpt)[:6]}" if isinstance(ckpt, dict) else ""))
    model = {(k[len(COMPILED_PREFIX):] if k.startswith(COMPILED_PREFIX) else k): v for k, v in ckpt["model"].items()}
    if len(model) < len(ckpt["model"]):  # 'x' and '_orig_mod.x' both: one of them would be dropped unseen
        twice = sorted(k for k in ckpt["model"] if isinstance(k, str) and k.startswith(COMPILED_PREFIX)
                       and k[len(COMPILED_PREFIX):] in ckpt["model"])
        raise ReleaseCheckpointError(f"{source}: 'model' holds weight '{twice[0][len(COMPILED_PREFIX):]}' twice, "
                                     f"as '{twice[0]}' too ({len(twice)} such); keep one spelling")
    if use_ema:
        ema = ckpt.get("ema_states")
        shadow = ema.get("shadow_params") if isinstance(ema, dict) else None
        if shadow is None:
            raise ReleaseCheckpointError(f"{source}: key 'ema_states' has no 'shadow_params' (load with "
                                         f"use_ema=false for the raw weights)")
        names = list(model)
        if len(shadow) != len(names):
            raise ReleaseCheckpointError(f"{source}: 'ema_states.shadow_params' holds {len(shadow)} tensors but "
                                         f"'model' has {len(names)} parameters")
        for name, tensor in zip(names, shadow):
            if tuple(tensor.shape) != tuple(model[name].shape):
                raise ReleaseCheckpointError(f"{source}: EMA tensor for '{name}' has shape {tuple(tensor.shape)}, "
                                             f"the model's {tuple(model[name].shape)}")
        model = dict(zip(names, shadow))
    if any(k.startswith(NETWORK_PREFIX) for k in model):
        model = {k[len(NETWORK_PREFIX):]: v for k, v in model.items() if k.startswith(NETWORK_PREFIX)}
    return model


def load_release_checkpoint(path, config: ReleaseNetworkConfig | dict | None = None, use_ema: bool = True,
                            map_location="cpu") -> ReleaseNetwork:
    """A :class:`ReleaseNetwork` (eval mode) with the weights of the release's ``ckpt.pth`` at ``path``
    (read by the platform's one loader, :func:`spread.safe_load.load_checkpoint`: ``weights_only=True`` whatever
    the environment says, a truncated file named); raises :class:`ReleaseCheckpointError` naming missing and
    unexpected keys."""
    from spread.safe_load import load_checkpoint

    ckpt = load_checkpoint(path, map_location=map_location)
    weights = release_state_dict(ckpt, str(path), use_ema)
    net = ReleaseNetwork(config)
    own = net.state_dict()
    wrong = [f"{k} {tuple(v.shape)} (network: {tuple(own[k].shape)})" for k, v in weights.items()
             if k in own and tuple(v.shape) != tuple(own[k].shape)]
    if wrong:
        raise ReleaseCheckpointError(f"{path}: {len(wrong)} weights have other shapes than the release network "
                                     f"({net.config.attn_dim} wide, {net.config.n_layers} blocks): {wrong[:4]}")
    result = net.load_state_dict(weights, strict=False)
    if result.missing_keys or result.unexpected_keys:
        raise ReleaseCheckpointError(f"{path}: the weights do not fit the release network ({net.config.attn_dim} "
                                     f"wide, {net.config.n_layers} blocks): missing {result.missing_keys[:8]}, "
                                     f"unexpected {result.unexpected_keys[:8]}")
    return net.eval()
