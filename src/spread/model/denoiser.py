"""The graph transformer that predicts the noise ε of every object's 9-D pose (paper §3.3).

Inputs (B scenes, N objects padded, ``mask`` (B, N) marks the real ones):

* ``x_t`` (B, N, 9): noisy states [normalised translation, rot6d]; ``t`` (B,) timesteps;
* ``edges`` (B, N, N, edge_dim) from :class:`~spread.model.graph_attention.EdgeEncoder`;
* ``shape_tokens`` (B, N, L, shape_dim): each object's asset tokens, projected by one shared Linear
  to the width (folded into each block's key/value projection, the same function at less cost);
* ``geometry_tokens`` (B, G, dim) or None: the scene's perceiver latents (``geometry`` variant).

Node token: ``Linear([Fourier(x_t), sinusoid(object index)])`` — the paper's "fixed sinusoidal
encodings → Linear"; the index code is the one the perceiver puts on each object's points — plus, with
``mount_feature``, a learned code of the object's mount (``mount`` (B, N): floor, on-object, wall, ceiling;
:func:`spread.scene.scene_mounts`), zero-initialised so a model starts as one without it.

Block (× depth), all pre-norm with AdaLN on the timestep embedding, residual after each sub-layer:
1. cross-attention of each object to its own shape tokens (real objects only);
2. cross-attention of every object to the scene's geometry tokens (``geometry`` variant only; the geometry
   tokens' keys/values and this sub-layer's AdaLN modulation are computed for all blocks in one product each:
   ``geometry_kv``, ``geometry_mod``; checkpoints with them per block load into it);
3. graph attention over the real objects, edge features as logit bias and message term;
4. GEGLU feed-forward.

Head: AdaLN → Linear → GELU → Linear (zero-initialised, so training starts from ε̂ = 0) → ε̂
(B, N, 9), zero at padding objects. Padding objects are never keys, so they cannot change the
output of a real object.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from spread.model.config import ModelConfig
from spread.model.encodings import TimestepEmbedding, fourier_dim, fourier_features, sinusoidal_embedding
from spread.model.graph_attention import GraphAttention
from spread.model.layers import AdaLayerNorm, Attention, FeedForward

STATE_DIM = 9


def real_objects(mask: torch.Tensor) -> torch.Tensor:
    """(V,) flat indices into B·N of the real objects of ``mask`` (B, N), in ``mask`` order (one host read)."""
    return mask.bool().flatten().nonzero().squeeze(1)


class DenoiserBlock(nn.Module):
    def __init__(self, cfg: ModelConfig, geometry: bool):
        super().__init__()
        dim, cond = cfg.dim, cfg.cond_dim
        self.norm_shape = AdaLayerNorm(dim, cond)
        self.shape_attn = Attention(dim, heads=cfg.heads, dim_head=cfg.dim_head, dropout=cfg.dropout)
        # geometry: the modulation and the keys/values are the denoiser's, computed for every block at once
        self.norm_geometry = nn.LayerNorm(dim, elementwise_affine=False) if geometry else None
        self.geometry_attn = (Attention(dim, heads=cfg.heads, dim_head=cfg.dim_head, dropout=cfg.dropout, kv="given")
                              if geometry else None)
        self.norm_graph = AdaLayerNorm(dim, cond)
        self.graph_attn = GraphAttention(dim, cfg.edge_dim, cond, heads=cfg.heads, dim_head=cfg.dim_head,
                                         dropout=cfg.dropout)
        self.norm_ff = AdaLayerNorm(dim, cond)
        self.ff = FeedForward(dim, cfg.ff_mult, cfg.dropout)

    def forward(self, x: torch.Tensor, cond: torch.Tensor, mask: torch.Tensor, shape_tokens: torch.Tensor,
                shape_in: nn.Linear, edges: torch.Tensor, geometry: tuple | None, real: torch.Tensor) -> torch.Tensor:
        """x (B, N, dim); cond (B, cond_dim); shape_tokens (V, L, shape_dim) of the V real objects (flat indices
        ``real`` (V,) into B·N, in ``mask`` order), projected by ``shape_in``; edges (B, N, N, edge_dim); geometry:
        None or this block's (keys/values (B, G, 2·heads·dim_head) of the scene's geometry tokens, 1 + scale (B, dim),
        shift (B, dim))."""
        h = self.norm_shape(x, cond)
        attended = self.shape_attn(h.flatten(0, 1).index_select(0, real)[:, None, :], shape_tokens,
                                   context_proj=shape_in)
        update = torch.zeros_like(x).flatten(0, 1).index_copy(0, real, attended[:, 0].to(x.dtype))
        x = x + update.view_as(x)
        if self.geometry_attn is not None:
            kv, scale, shift = geometry
            h = torch.addcmul(shift[:, None, :], self.norm_geometry(x), scale[:, None, :])  # AdaLN
            x = x + self.geometry_attn(h, kv=kv)
        x = x + self.graph_attn(self.norm_graph(x, cond), edges, mask, cond)
        return x + self.ff(self.norm_ff(x, cond))


class GraphDenoiser(nn.Module):
    """ε̂(x_t, t, graphs, shape tokens[, geometry tokens]) → (B, N, 9) (see the module docstring)."""

    def __init__(self, cfg: ModelConfig, geometry: bool):
        super().__init__()
        self.cfg, self.geometry = cfg, geometry
        self.time = TimestepEmbedding(cfg.cond_dim)
        self.node_in = nn.Linear(fourier_dim(STATE_DIM, cfg.state_bands) + cfg.index_dim, cfg.dim)
        self.mount_in = None
        if cfg.mount_feature:
            from spread.scene import MOUNT_NAMES

            self.mount_in = nn.Embedding(len(MOUNT_NAMES), cfg.dim)
            nn.init.zeros_(self.mount_in.weight)
        self.shape_in = nn.Linear(cfg.shape_dim, cfg.dim)
        self.blocks = nn.ModuleList(DenoiserBlock(cfg, geometry) for _ in range(cfg.depth))
        if geometry:  # every block's AdaLN modulation and keys/values of the geometry tokens, in one product each
            inner = cfg.heads * cfg.dim_head
            self.geometry_kv = nn.Linear(cfg.dim, cfg.depth * 2 * inner, bias=False)
            self.geometry_mod = nn.Linear(cfg.cond_dim, cfg.depth * 2 * cfg.dim)
            nn.init.zeros_(self.geometry_mod.weight)
            nn.init.zeros_(self.geometry_mod.bias)
            self.register_load_state_dict_pre_hook(_legacy_geometry_layout)
        self.norm_out = AdaLayerNorm(cfg.dim, cfg.cond_dim)
        self.head = nn.Sequential(nn.Linear(cfg.dim, cfg.dim), nn.GELU(), nn.Linear(cfg.dim, STATE_DIM))
        nn.init.zeros_(self.head[-1].weight)
        nn.init.zeros_(self.head[-1].bias)

    def embed_nodes(self, x_t: torch.Tensor, mount: torch.Tensor | None = None) -> torch.Tensor:
        B, N, _ = x_t.shape
        index = sinusoidal_embedding(torch.arange(N, device=x_t.device), self.cfg.index_dim).expand(B, N, -1)
        state = fourier_features(x_t, self.cfg.state_bands, self.cfg.state_max_frequency)
        x = self.node_in(torch.cat([state, index.to(state.dtype)], dim=-1))
        if self.mount_in is not None and mount is not None:
            x = x + self.mount_in(mount.long()).to(x.dtype)
        return x

    def geometry_inputs(self, tokens: torch.Tensor, cond: torch.Tensor) -> list[tuple]:
        """Per block: (keys/values of the geometry tokens (B, G, 2·heads·dim_head), 1 + scale, shift (B, dim)) of its
        geometry cross-attention's AdaLN — each computed for all blocks in one product."""
        depth, dim = len(self.blocks), self.cfg.dim
        kv = self.geometry_kv(tokens).chunk(depth, dim=-1)
        scale, shift = self.geometry_mod(F.silu(cond)).view(-1, depth, 2, dim).unbind(2)
        return list(zip(kv, (scale + 1).unbind(1), shift.unbind(1)))

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, mask: torch.Tensor, edges: torch.Tensor,
                shape_tokens: torch.Tensor, geometry_tokens: torch.Tensor | None = None,
                mount: torch.Tensor | None = None, real: torch.Tensor | None = None,
                node_features: torch.Tensor | None = None) -> torch.Tensor:
        """ε̂ (B, N, 9). ``real`` (V,): the flat indices of the real objects in B·N (:func:`real_objects`), made once
        per sample so that a step reads no tensor value on the host; found from ``mask`` when not given."""
        if self.geometry and geometry_tokens is None:
            raise ValueError("GraphDenoiser(geometry=True) needs geometry_tokens")
        mask = mask.bool()
        real = real_objects(mask) if real is None else real
        cond = self.time(t)
        x = self.embed_nodes(x_t, mount)
        if node_features is not None:  # (B, N, dim) added to each node's input (the geometry summary)
            x = x + node_features
        shape_tokens = shape_tokens.flatten(0, 1).index_select(0, real)  # (V, L, shape_dim), projected in each block
        geometry = self.geometry_inputs(geometry_tokens, cond) if self.geometry else [None] * len(self.blocks)
        for block, block_geometry in zip(self.blocks, geometry):
            x = block(x, cond, mask, shape_tokens, self.shape_in, edges, block_geometry, real)
        eps = self.head(self.norm_out(x, cond))
        return eps * mask[..., None]


def _legacy_geometry_layout(module, state_dict, prefix, *args) -> None:
    """Load hook: a checkpoint with an AdaLN and a ``to_kv`` in each block's geometry attention
    (``blocks.i.norm_geometry.to_scale_shift.1``, ``blocks.i.geometry_attn.to_kv``) → the stacked
    ``geometry_mod`` and ``geometry_kv`` (the same function)."""
    head = f"{prefix}blocks."
    if f"{prefix}geometry_kv.weight" in state_dict or f"{head}0.geometry_attn.to_kv.weight" not in state_dict:
        return
    depth = len(module.blocks)
    kv = [state_dict.pop(f"{head}{i}.geometry_attn.to_kv.weight") for i in range(depth)]
    weight = [state_dict.pop(f"{head}{i}.norm_geometry.to_scale_shift.1.weight") for i in range(depth)]
    bias = [state_dict.pop(f"{head}{i}.norm_geometry.to_scale_shift.1.bias") for i in range(depth)]
    state_dict[f"{prefix}geometry_kv.weight"] = torch.cat(kv, 0)
    state_dict[f"{prefix}geometry_mod.weight"] = torch.cat(weight, 0)
    state_dict[f"{prefix}geometry_mod.bias"] = torch.cat(bias, 0)
