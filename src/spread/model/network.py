"""``SceneDenoiser``: the whole ε-network of one variant — shape encoder, edge encoder, geometry
perceiver (``geometry`` only) and graph transformer — over a batch of :mod:`spread.data` tensors.

Sampling calls the network once per step on the same scenes, so what does not depend on the noisy
state is computed once by :meth:`SceneDenoiser.condition` (shape tokens, edge features) and reused;
:meth:`SceneDenoiser.forward` then only does the per-step work: in the ``geometry`` variant it
denormalises the current translations with ``bounds`` (the stats.json bounds, a buffer saved with
the weights), turns the rot6d into matrices by Gram–Schmidt, recomputes the signed chamfer features
of the posed points (or, with ``geometry_distance=parts``, their distances to the other objects' convex parts) and
runs the perceiver, then the graph transformer.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Iterator, Sequence

import torch
from torch import nn

from spread.data.collate import PHYSICAL_PAD, SPATIAL_PAD
from spread.model.config import ModelConfig
from spread.model.denoiser import GraphDenoiser, real_objects
from spread.data.parts import check_geometry_distance
from spread.model.geometry import (SEARCHES, PointCloud, batch_cloud, blind_distances, resolve_search,
                                   state_distances)
from spread.model.graph_attention import EdgeEncoder
from spread.model.perceiver import (PAIR_DIM, SUMMARY_DIM, GeometryPerceiver, StaticTokens, object_summary,
                                    pair_features)
from spread.model.poses import denormalize_affine
from spread.model.shape_tokens import PointCloudTokenizer, PrecomputedShapeTokens, ShapeEncoder

VARIANTS = ("base", "geometry")
#: where the geometry features pose the scene (ModelConfig.geometry_at): the noisy states, or the clean estimate
GEOMETRY_AT = ("x_t", "x0_hat")


@dataclass
class Condition:
    """Everything the network needs besides (x_t, t); constant through one sampling run."""

    mask: torch.Tensor  # (B, N) bool
    spatial: torch.Tensor  # (B, N, N) long
    physical: torch.Tensor  # (B, N, N) long
    edges: torch.Tensor  # (B, N, N, edge_dim)
    shape_tokens: torch.Tensor  # (B, N, L, shape_dim)
    cloud: PointCloud | None = None  # geometry variant: the canonical points and normals, masked (once per sample)
    static: StaticTokens | None = None  # geometry variant: the perceiver's pose-independent token channels
    mount: torch.Tensor | None = None  # (B, N) long mount codes (batch["mount"]), when the batch has them
    search: str = "pruned"  # the nearest-point search (ModelConfig.nearest, resolved for the batch's device)
    pose_scale: torch.Tensor | None = None  # geometry variant: (3,) metres per unit of normalised translation
    pose_offset: torch.Tensor | None = None  # (3,) metres at normalised 0
    real: torch.Tensor | None = None  # (V,) flat indices of the real objects in B·N (so no step reads the mask)
    #: geometry variant, sampling: the geometry-blind features (they read no pose), made at the first blind pass and
    #: reused by every later step — keyed by the states' dtype and the autocast in force; shared with
    #: :meth:`SceneDenoiser.null_condition` (the blind features read no graph either)
    blind: dict = field(default_factory=dict, repr=False, compare=False)
    #: geometry variant, sampling: while :func:`sharing_geometry` holds, the posed features last made without
    #: gradients, with the states tensor and network they were made for; shared with
    #: :meth:`SceneDenoiser.null_condition`
    posed: dict = field(default_factory=dict, repr=False, compare=False)


@contextmanager
def sharing_geometry(cond: Condition) -> Iterator[None]:
    """Within it, the geometry features of a scene posed at a states tensor are made once (without gradients, by one
    network) and reused by every condition that shares ``cond``'s store — :meth:`SceneDenoiser.null_condition`'s: the
    features read no graph, so classifier-free guidance on the graphs searches and runs the perceiver once a step, not
    twice. Nothing is kept after it (the weights or the states may change in place between steps)."""
    cond.posed.clear()
    cond.posed["open"] = True  # what geometry_features asks; "made": the last features, with what they were made of
    try:
        yield
    finally:
        cond.posed.clear()


def upgrade_state_dict(network: nn.Module, state: dict) -> dict:
    """A copy of ``state`` (a state dict of ``network``, keys relative to it) with an older layout's keys renamed as
    ``load_state_dict`` would (every module's load hooks: fused self-attention projections, the perceiver's and the
    denoiser's stacked geometry weights), for callers that match keys themselves."""
    state = dict(state)
    for name, module in network.named_modules():
        for hook in module._load_state_dict_pre_hooks.values():
            hook(state, f"{name}." if name else "", {}, True, [], [], [])
    return state


def blind_key(x_t: torch.Tensor) -> tuple:
    """What the geometry-blind features depend on besides the condition: the states' dtype and the autocast in
    force on their device (``sampling.precision=bf16`` runs the perceiver in bfloat16)."""
    device = x_t.device.type
    enabled = torch.is_autocast_enabled(device)
    return x_t.dtype, enabled, torch.get_autocast_dtype(device) if enabled else None


def reusable() -> bool:
    """Whether features made now (without gradients) may be kept for later steps: not inside torch.compile (a side
    effect it would trace) and not while a CUDA graph records (its memory is the graph's; the eager warm-up before
    the recording keeps them)."""
    if torch.compiler.is_compiling():
        return False
    return not (torch.cuda.is_available() and torch.cuda.is_current_stream_capturing())


def drop_graphs(spatial: torch.Tensor, physical: torch.Tensor, drop: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace both graphs of the scenes in ``drop`` (B,) bool by the padding codes (the null graph of
    classifier-free guidance)."""
    keep = ~drop[:, None, None]
    return (torch.where(keep, spatial, torch.full_like(spatial, SPATIAL_PAD)),
            torch.where(keep, physical, torch.full_like(physical, PHYSICAL_PAD)))


def build_shape_encoder(cfg: ModelConfig) -> ShapeEncoder:
    if cfg.shape_encoder == "points":
        return PointCloudTokenizer(cfg.shape_tokens, cfg.shape_dim, cfg.tokenizer_width, cfg.tokenizer_heads,
                                   cfg.tokenizer_points, cfg.point_bands, cfg.point_max_frequency)
    if cfg.shape_encoder == "precomputed":
        return PrecomputedShapeTokens(cfg.shape_tokens, cfg.shape_dim)
    raise ValueError(f"unknown shape_encoder '{cfg.shape_encoder}' (choose 'points' or 'precomputed')")


class SceneDenoiser(nn.Module):
    """ε̂(x_t, t | batch) for variant ``base`` or ``geometry``; ``bounds`` = stats.json
    ``bounds_translations`` (6 floats, metres), needed by ``geometry`` (NaN until set)."""

    def __init__(self, config: ModelConfig, variant: str = "geometry", bounds: Sequence[float] | None = None):
        super().__init__()
        if variant not in VARIANTS:
            raise ValueError(f"unknown variant '{variant}' (choose from {VARIANTS})")
        self.config, self.variant = config, variant
        check_geometry_distance(getattr(config, "geometry_distance", "chamfer"))
        if getattr(config, "nearest", "auto") not in SEARCHES:  # refused here, not at the first training step
            raise ValueError(f"model.config.nearest: unknown search {config.nearest!r} (choose from {SEARCHES})")
        self.shape_encoder = build_shape_encoder(config)
        self.edge_encoder = EdgeEncoder(config.edge_dim)
        self.perceiver = None
        if variant == "geometry":
            self.perceiver = GeometryPerceiver(
                config.dim, config.num_latents, config.perceiver_depth, config.perceiver_self_per_cross,
                config.perceiver_cross_heads, config.perceiver_cross_dim_head, config.heads, config.dim_head,
                config.ff_mult, config.point_bands, config.point_max_frequency, config.index_dim,
                config.perceiver_dropout)
        self.denoiser = GraphDenoiser(config, geometry=variant == "geometry")
        if getattr(config, "geometry_at", "x_t") not in GEOMETRY_AT:
            raise ValueError(f"model.config.geometry_at={config.geometry_at!r}: choose from {list(GEOMETRY_AT)}")
        self.summary_in = None
        if variant == "geometry" and getattr(config, "geometry_summary", False):
            self.summary_in = nn.Linear(SUMMARY_DIM, config.dim)
            nn.init.zeros_(self.summary_in.weight)
            nn.init.zeros_(self.summary_in.bias)
        self.pairs_in = None
        if variant == "geometry" and getattr(config, "geometry_pairs", False):
            if getattr(config, "geometry_distance", "chamfer") != "parts":
                raise ValueError("model.config.geometry_pairs=true needs model.config.geometry_distance=parts (the "
                                 f"pair distances are the parts distance's), got {config.geometry_distance!r}")
            self.pairs_in = nn.Linear(PAIR_DIM, config.edge_dim)
            nn.init.zeros_(self.pairs_in.weight)
            nn.init.zeros_(self.pairs_in.bias)
        self.register_buffer("bounds", torch.full((6,), float("nan")))
        if bounds is not None:
            self.set_bounds(bounds)

    def set_bounds(self, bounds: Sequence[float] | torch.Tensor) -> None:
        b = torch.as_tensor(bounds, dtype=torch.float32).reshape(6)
        if not torch.isfinite(b).all() or (b[3:] <= b[:3]).any():
            raise ValueError(f"bounds must be 6 finite numbers [min xyz, max xyz] with max > min, got {b.tolist()}")
        self.bounds.copy_(b.to(self.bounds.device))

    def condition(self, batch: dict, drop_graph: torch.Tensor | None = None) -> Condition:
        """Shape tokens and edge features of a batch; ``drop_graph`` (B,) bool nulls those scenes' graphs."""
        mask = batch["mask"].bool()
        spatial, physical = batch["spatial"].long(), batch["physical"].long()
        if drop_graph is not None:
            spatial, physical = drop_graphs(spatial, physical, drop_graph)
        cond = Condition(mask=mask, spatial=spatial, physical=physical, edges=self.edge_encoder(spatial, physical),
                         shape_tokens=self.shape_encoder(batch), mount=batch.get("mount"), real=real_objects(mask))
        if self.perceiver is not None:
            if not torch.compiler.is_compiling() and not torch.isfinite(self.bounds).all():  # eager: checked
                raise RuntimeError("SceneDenoiser: translation bounds are not set "
                                   "(call set_bounds(stats['bounds_translations']))")
            cond.search = resolve_search(getattr(self.config, "nearest", "pruned"), mask.device)
            # sampling: each object's points in Morton order once, so the dense search skips most tiles (a
            # dataset's points come so ordered: spread.data.points; training sorts nothing per step)
            parts = getattr(self.config, "geometry_distance", "chamfer") == "parts"
            cond.cloud = batch_cloud(batch, mask, parts=parts, morton=cond.search == "dense" and not self.training)
            cond.static = self.perceiver.static(cond.cloud.points, mask)
            cond.pose_offset, cond.pose_scale = denormalize_affine(self.bounds)  # one multiply-add per step
        return cond

    def null_condition(self, cond: Condition) -> Condition:
        """The same scenes with both graphs dropped (classifier-free guidance's unconditional branch)."""
        drop = torch.ones(cond.mask.shape[0], dtype=torch.bool, device=cond.mask.device)
        spatial, physical = drop_graphs(cond.spatial, cond.physical, drop)
        return replace(cond, spatial=spatial, physical=physical, edges=self.edge_encoder(spatial, physical))

    def geometry_tokens(self, x_t: torch.Tensor, cond: Condition) -> torch.Tensor:
        """Perceiver latents (B, G, dim) of the scene posed at the (noisy) states x_t (B, N, 9)."""
        return self.geometry_features(x_t, cond)[0]

    def geometry_features(self, x_t: torch.Tensor, cond: Condition, blind: bool = False) -> tuple[torch.Tensor, ...]:
        """The perceiver latents (B, G, dim) of the scene posed at x_t (B, N, 9); with ``geometry_summary`` each
        node's summary input (B, N, dim), with ``geometry_pairs`` each edge's pair input (B, N, N, edge_dim)
        (else None). ``blind``: the same features with every distance read as if no other object were near
        (:func:`~spread.model.geometry.blind_distances`; x_t then only sets the dtype) — the geometry-free branch
        of classifier-free guidance on the geometry; they read no pose, so without gradients they are made once
        per condition and reused (``cond.blind``)."""
        if blind and not torch.is_grad_enabled():
            key = blind_key(x_t)
            if key not in cond.blind:
                features = self._geometry_features(x_t, cond, True)
                if not reusable():
                    return features
                cond.blind[key] = features
            return cond.blind[key]
        if not blind and cond.posed.get("open") and not torch.is_grad_enabled():  # sharing_geometry: made once
            key = (x_t._version, blind_key(x_t))
            made = cond.posed.get("made")
            if made is not None and made[0] is x_t and made[1] is self and made[2] == key:
                return made[3]
            features = self._geometry_features(x_t, cond, False)
            if reusable():
                cond.posed["made"] = (x_t, self, key, features)
            return features
        return self._geometry_features(x_t, cond, blind)

    def _geometry_features(self, x_t: torch.Tensor, cond: Condition, blind: bool) -> tuple[torch.Tensor, ...]:
        pairs = None
        if blind:
            distance = blind_distances(cond.cloud, pairs=self.pairs_in is not None)
        else:
            distance = state_distances(cond.cloud, x_t, cond.pose_offset, cond.pose_scale, cond.search,
                                       pairs=self.pairs_in is not None)
        if self.pairs_in is not None:
            distance, pairs = distance[0], self.pairs_in(pair_features(distance[1].to(x_t.dtype)))
        distance = distance.to(x_t.dtype)
        tokens = self.perceiver(distance, cond.static)
        summary = None
        if self.summary_in is not None:
            summary = self.summary_in(object_summary(distance, cond.cloud.points.to(x_t.dtype)))
        return tokens, summary, pairs

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, cond: Condition, pose: torch.Tensor | None = None,
                blind: bool = False) -> torch.Tensor:
        """x_t (B, N, 9), t (B,) → ε̂ (B, N, 9), zero at padding objects; the geometry features of the scene posed at
        ``pose`` (B, N, 9) states (None: at x_t; ``geometry_at=x0_hat``: the module passes its clean estimate), or with
        ``blind`` those of a scene with nothing near anything (:meth:`geometry_features`; needs the perceiver)."""
        if blind and self.perceiver is None:
            raise ValueError("SceneDenoiser: blind=True reads no geometry of a model without geometry features "
                             "(model.variant=base)")
        posed = x_t if pose is None else pose.to(x_t)
        geometry, summary, pairs = (self.geometry_features(posed, cond, blind) if self.perceiver is not None
                                    else (None, None, None))
        edges = cond.edges if pairs is None else cond.edges + pairs
        return self.denoiser(x_t, t, cond.mask, edges, cond.shape_tokens, geometry, mount=cond.mount,
                             real=cond.real, node_features=summary)
