"""Shape tokens: a fixed-size set of L tokens (each ``token_dim`` wide) describing each object's asset.

Two encoders share one interface, ``encoder(batch) -> (B, N, L, token_dim)`` with zeros at padding
objects; the denoiser projects the tokens to its width with one Linear (paper §3.3: Michelangelo's
256 × 64 latents "linearly projected to the attention dimension").

* :class:`PointCloudTokenizer` (default): learned from each asset's canonical surface samples
  (``batch['points']``, ``batch['normals']``, (B, N, M, 3), metres). A function of the asset only —
  canonical frame, no pose, no timestep — so the tokens are constant through diffusion, like the
  paper's frozen Michelangelo latents; unlike them, it is trained jointly with the denoiser by the
  same ε loss (no pretrained encoder is available offline). When the batch says which objects carry the same
  point set (``batch['shape_index']``, :class:`~spread.data.SceneDataset`), each distinct set is encoded once
  and its tokens shared — the same function, 25–55 % less work at batch 8–32 of generated rooms, where assets
  repeat. Architecture (3DShape2VecSet-style):
  Fourier features of xyz + normal → Linear → L learned queries cross-attend to the points → self-
  attention → Linear to ``token_dim``. The cross-attention has two ways to the same function
  (:func:`cross_mode`): keys and values formed from the points, or the queries carried into the points'
  channels (:meth:`~spread.model.layers.Attention.attend_raw`), chosen by device and size. It reads the
  first ``num_points`` samples of each object (the dataset's per-asset subsets are random, so this is a
  fixed random subset per asset).
* :class:`PrecomputedShapeTokens`: tokens computed offline (e.g. the reference's ``miche_feature``,
  256 × 64) passed in ``batch['shape_tokens']`` (B, N, L, token_dim); returned as they are.
"""

from __future__ import annotations

import torch
from einops import repeat
from torch import nn

from spread.model.encodings import fourier_dim, fourier_features
from spread.model.layers import CROSS_MODES, Attention, FeedForward


def cross_mode(device: torch.device, num_tokens: int, width: int, heads: int) -> str:
    """``absorbed`` on the CPU when carrying the L queries into the points' ``width`` channels does no more attention
    arithmetic than forming keys and values and attending with them — L·width ≤ dim_head·(width + L), dim_head =
    width / heads — else ``formed`` (and always on CUDA, where neither is timed). The tiny config (16 queries,
    width 64: 0.8 of the formed way's arithmetic) runs its tokenizer 1.4–1.5× faster forward + backward absorbed
    (no (objects, points, 2·width) keys/values, no copies into heads); the paper's (256 queries, width 128: 2.7×)
    1.7× slower (``benchmarks/RESULTS.md``, stop 58)."""
    if torch.device(device).type != "cpu":
        return "formed"
    return "absorbed" if num_tokens * width <= (width // heads) * (width + num_tokens) else "formed"


class ShapeEncoder(nn.Module):
    """Interface: ``forward(batch) -> (B, N, num_tokens, token_dim)``, zeros at padding objects."""

    num_tokens: int
    token_dim: int

    def forward(self, batch: dict) -> torch.Tensor:  # pragma: no cover - interface
        raise NotImplementedError


class PointCloudTokenizer(ShapeEncoder):
    """Canonical points + normals of each real object → L tokens (see the module docstring)."""

    def __init__(self, num_tokens: int = 16, token_dim: int = 64, width: int = 128, heads: int = 4,
                 num_points: int = 512, num_bands: int = 6, max_frequency: float = 32.0):
        super().__init__()
        self.num_tokens, self.token_dim, self.num_points = num_tokens, token_dim, num_points
        self.num_bands, self.max_frequency = num_bands, max_frequency
        self.embed = nn.Linear(fourier_dim(3, num_bands) + 3, width)
        self.queries = nn.Parameter(torch.randn(num_tokens, width) * 0.02)
        self.norm_points = nn.LayerNorm(width)
        self.cross = Attention(width, heads=heads, dim_head=width // heads)
        self.norm_self = nn.LayerNorm(width)
        self.self_attn = Attention(width, heads=heads, dim_head=width // heads, kv="self")
        self.norm_ff = nn.LayerNorm(width)
        self.ff = FeedForward(width, mult=2)
        self.out = nn.Sequential(nn.LayerNorm(width), nn.Linear(width, token_dim))

    def encode(self, points: torch.Tensor, normals: torch.Tensor, mode: str | None = None) -> torch.Tensor:
        """(V, P, 3) points and normals of V objects → (V, L, token_dim); ``mode``: one of :data:`CROSS_MODES`
        (None: :func:`cross_mode` of the device and this tokenizer's sizes)."""
        width = self.queries.shape[1]
        mode = cross_mode(points.device, self.num_tokens, width, self.cross.heads) if mode is None else mode
        if mode not in CROSS_MODES:
            raise ValueError(f"PointCloudTokenizer: mode must be one of {CROSS_MODES}, got {mode!r}")
        feats = torch.cat([fourier_features(points, self.num_bands, self.max_frequency), normals], dim=-1)
        context = self.norm_points(self.embed(feats))
        z = repeat(self.queries, "l d -> v l d", v=points.shape[0])
        if mode == "formed":
            z = z + self.cross(z, context)
        else:
            key_weight, value_weight = self.cross.to_kv.weight.chunk(2, dim=0)
            z = z + self.cross.attend_raw(z, context, key_weight, value_weight)
        h = self.norm_self(z)
        z = z + self.self_attn(h)
        z = z + self.ff(self.norm_ff(z))
        return self.out(z)

    def forward(self, batch: dict) -> torch.Tensor:
        mask = batch["mask"]
        points = batch["points"][:, :, : self.num_points]
        normals = batch["normals"][:, :, : self.num_points]
        B, N = mask.shape
        if torch.compiler.is_compiling():  # a compiled step has no data-dependent shapes: every slot, padding zeroed
            keep = mask[..., None, None]
            points = torch.where(keep, points.float(), 0.0).flatten(0, 1)
            normals = torch.where(keep, normals.float(), 0.0).flatten(0, 1)
            tokens = self.encode(points, normals).view(B, N, self.num_tokens, self.token_dim)
            return torch.where(keep, tokens, 0.0).to(batch["points"].dtype)
        out = points.new_zeros(B, N, self.num_tokens, self.token_dim)
        points, normals = points[mask].float(), normals[mask].float()
        keys = batch.get("shape_index")
        if keys is None:
            out[mask] = self.encode(points, normals).to(out.dtype)
            return out
        unique, inverse = torch.unique(keys[mask], return_inverse=True)
        first = torch.full((len(unique),), len(inverse), dtype=torch.long, device=inverse.device)
        first.scatter_reduce_(0, inverse, torch.arange(len(inverse), device=inverse.device), "amin")
        out[mask] = self.encode(points[first], normals[first])[inverse].to(out.dtype)
        return out


class PrecomputedShapeTokens(ShapeEncoder):
    """``batch['shape_tokens']`` (B, N, L, token_dim), zeroed at padding objects."""

    def __init__(self, num_tokens: int = 256, token_dim: int = 64, key: str = "shape_tokens"):
        super().__init__()
        self.num_tokens, self.token_dim, self.key = num_tokens, token_dim, key

    def forward(self, batch: dict) -> torch.Tensor:
        if self.key not in batch:
            raise KeyError(f"PrecomputedShapeTokens: the batch has no '{self.key}' (B, N, L, D) tensor")
        tokens = batch[self.key]
        expected = (self.num_tokens, self.token_dim)
        if tuple(tokens.shape[2:]) != expected:
            raise ValueError(f"PrecomputedShapeTokens: batch['{self.key}'] has tokens {tuple(tokens.shape[2:])}, "
                             f"expected {expected}")
        return torch.where(batch["mask"][..., None, None], tokens, 0.0)
