"""Relation graphs → edge features, and graph attention that reads them (paper §3.2, eq. E = MLP(Emb(G))).

Edges are directed. ``spatial[i, j]`` (8 codes: 0..6 of DESIGN §3, 7 = padding / dropped graph)
says "i is … of j"; ``physical[i, j]`` (4 codes: 0 none, 1 i supports j, 2 contact, 3 padding) is
filled in one direction only (the supporter's row). The feature of the ordered pair (i, j) therefore
embeds both ``code[i, j]`` and ``code[j, i]`` of both graphs with four separate tables — node i
learns "i supports j" and "j supports i" from the same edge — then an MLP: ``E (B, N, N, edge_dim)``.

:class:`GraphAttention` — node i (query) attends to every real node j (keys; padding keys masked),
with the edge entering twice: a per-head additive bias on the logits, ``b_ij = W_b e_ij``, and a
message term, ``out_i = Σ_j a_ij (v_j + W_v e_ij)`` (so what flows from j depends on how j relates
to i). The edge features are AdaLN-normalised on the timestep first, so each block and each noise
level can read the graph differently.
"""

from __future__ import annotations

import torch
from einops import rearrange
from torch import nn

from spread.data.collate import PHYSICAL_PAD, SPATIAL_PAD
from spread.model.layers import AdaLayerNorm

SPATIAL_VOCAB = SPATIAL_PAD + 1  # 8
PHYSICAL_VOCAB = PHYSICAL_PAD + 1  # 4


class EdgeEncoder(nn.Module):
    """spatial, physical (B, N, N) long → edge features (B, N, N, edge_dim)."""

    def __init__(self, edge_dim: int):
        super().__init__()
        self.spatial_out = nn.Embedding(SPATIAL_VOCAB, edge_dim)  # code[i, j]
        self.spatial_in = nn.Embedding(SPATIAL_VOCAB, edge_dim)  # code[j, i]
        self.physical_out = nn.Embedding(PHYSICAL_VOCAB, edge_dim)
        self.physical_in = nn.Embedding(PHYSICAL_VOCAB, edge_dim)
        self.mlp = nn.Sequential(nn.GELU(), nn.Linear(edge_dim, edge_dim), nn.GELU(), nn.Linear(edge_dim, edge_dim))

    def forward(self, spatial: torch.Tensor, physical: torch.Tensor) -> torch.Tensor:
        e = (self.spatial_out(spatial) + self.spatial_in(spatial.transpose(1, 2))
             + self.physical_out(physical) + self.physical_in(physical.transpose(1, 2)))
        return self.mlp(e)


class GraphAttention(nn.Module):
    """Nodes x (B, N, dim), edges e (B, N, N, edge_dim), key_mask (B, N) → (B, N, dim)."""

    def __init__(self, dim: int, edge_dim: int, cond_dim: int, heads: int = 8, dim_head: int = 64,
                 dropout: float = 0.0):
        super().__init__()
        inner = heads * dim_head
        self.heads, self.scale = heads, dim_head ** -0.5
        self.to_qkv = nn.Linear(dim, 3 * inner, bias=False)
        self.edge_norm = AdaLayerNorm(edge_dim, cond_dim)
        self.edge_bias = nn.Linear(edge_dim, heads)
        self.edge_value = nn.Linear(edge_dim, inner, bias=False)
        self.dropout = nn.Dropout(dropout)
        self.to_out = nn.Sequential(nn.Linear(inner, dim), nn.Dropout(dropout))

    def forward(self, x: torch.Tensor, edges: torch.Tensor, key_mask: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        q, k, v = rearrange(self.to_qkv(x), "b n (three h d) -> three b h n d", three=3, h=self.heads)
        e = self.edge_norm(edges, cond)
        logits = torch.einsum("bhid,bhjd->bhij", q, k) * self.scale
        logits = logits + rearrange(self.edge_bias(e), "b i j h -> b h i j")
        logits = logits.masked_fill(~key_mask[:, None, None, :], float("-inf"))
        attn = self.dropout(logits.softmax(dim=-1))
        edge_v = rearrange(self.edge_value(e), "b i j (h d) -> b h i j d", h=self.heads)
        out = torch.einsum("bhij,bhjd->bhid", attn, v) + torch.einsum("bhij,bhijd->bhid", attn, edge_v)
        return self.to_out(rearrange(out, "b h n d -> b n (h d)"))
