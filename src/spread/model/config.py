"""Model sizes. ``ModelConfig.paper()`` is the paper/release network; ``ModelConfig.tiny()`` trains
usefully on a 2-core CPU. Any field can be overridden: ``ModelConfig.from_any("tiny", depth=4)``.

Widths are channels; ``num_points`` is M, the surface samples per object the data module should load
(the model itself takes whatever M the batch carries).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace
from typing import Any, Mapping


@dataclass(frozen=True)
class ModelConfig:
    name: str = "custom"
    # graph transformer (denoiser)
    dim: int = 512
    depth: int = 6
    heads: int = 8
    dim_head: int = 64
    edge_dim: int = 128
    cond_dim: int = 128  # timestep embedding
    ff_mult: int = 4
    dropout: float = 0.1
    state_bands: int = 8  # Fourier bands of the node state x (9 channels)
    state_max_frequency: float = 32.0
    index_dim: int = 64  # sinusoidal code of the object index (nodes and geometry points)
    # shape tokens
    shape_encoder: str = "points"  # "points" (PointCloudTokenizer) | "precomputed" (batch['shape_tokens'])
    shape_tokens: int = 256  # L
    shape_dim: int = 64  # token width before the denoiser's projection
    tokenizer_width: int = 128
    tokenizer_heads: int = 4
    tokenizer_points: int = 1024
    # geometry perceiver (variant "geometry")
    num_latents: int = 256
    perceiver_depth: int = 4
    perceiver_self_per_cross: int = 2
    perceiver_cross_heads: int = 1
    perceiver_cross_dim_head: int = 64
    point_bands: int = 6  # Fourier bands of canonical xyz (metres)
    point_max_frequency: float = 32.0
    # data
    num_points: int = 2000  # M

    @classmethod
    def paper(cls, **overrides) -> "ModelConfig":
        """Width 512, 6 blocks, 8 heads, 256 scene latents (4 × [cross + 2 self]), 256 × 64 shape
        tokens, M = 2,000 (reference §2, paper supplement)."""
        return replace(cls(name="paper"), **overrides)

    @classmethod
    def tiny(cls, **overrides) -> "ModelConfig":
        """Width 128, 3 blocks, 4 heads, 32 latents, 16 × 64 shape tokens, M = 256."""
        base = cls(name="tiny", dim=128, depth=3, heads=4, dim_head=32, edge_dim=64, cond_dim=128, ff_mult=2,
                   dropout=0.0, index_dim=32, shape_tokens=16, shape_dim=64, tokenizer_width=64,
                   tokenizer_heads=4, tokenizer_points=256, num_latents=32, perceiver_depth=1,
                   perceiver_self_per_cross=1, perceiver_cross_heads=1, perceiver_cross_dim_head=32,
                   num_points=256)
        return replace(base, **overrides)

    @classmethod
    def from_any(cls, config: "str | Mapping[str, Any] | ModelConfig", **overrides) -> "ModelConfig":
        """A preset name ("paper", "tiny"), a mapping of fields (e.g. from a checkpoint), or a config."""
        if isinstance(config, ModelConfig):
            return replace(config, **overrides)
        if isinstance(config, str):
            presets = {"paper": cls.paper, "tiny": cls.tiny}
            if config not in presets:
                raise ValueError(f"unknown model config '{config}' (choose from {sorted(presets)})")
            return presets[config](**overrides)
        known = {f.name for f in fields(cls)}
        unknown = set(config) - known
        if unknown:
            raise ValueError(f"ModelConfig: unknown fields {sorted(unknown)}")
        return cls(**{**dict(config), **overrides})

    def to_dict(self) -> dict:
        return asdict(self)
