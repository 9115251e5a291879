"""Model settings: :class:`ModelConfig` (the network's sizes) and :class:`SceneDiffusionConfig` (the
LightningModule's arguments). Both are the single source of their defaults: Hydra's ``model`` group extends
them (``conf/model/paper.yaml`` is ModelConfig's defaults = the paper's network, ``conf/model/tiny.yaml``
overrides them to a size that trains usefully on a 2-core CPU; :mod:`spread.configs` registers the schema).

Widths are channels; ``num_points`` is M, the surface samples per object the data module should load
(the model itself takes whatever M the batch carries).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Mapping


@dataclass
class ModelConfig:
    """The network's sizes. Defaults: the paper's / release's network (reference §2, paper supplement):
    width 512, 6 blocks of 8 heads, 128-d edges, 256 × 64 shape tokens, a scene Perceiver of 256 latents
    (4 × [cross + 2 self]), M = 2,000 points per object."""

    name: str = "paper"
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
    mount_feature: bool = True  # a learned code of each object's mount (floor, on-object, wall, ceiling) on its node
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
    perceiver_dropout: float = 0.0  # the release's perceiver has none (reference §2.3); the graph blocks use `dropout`
    point_bands: int = 6  # Fourier bands of canonical xyz (metres)
    point_max_frequency: float = 32.0
    # data
    num_points: int = 2000  # M
    # how the geometry features' exact nearest other-object point is searched (the same answer every way):
    # "tree" (a k-d tree per object, on the host: best on CPU), "pruned" (object pruning, Python loop over point
    # blocks, on the tensors' device), "dense" (one operator: a Triton kernel on CUDA, on CPU the trees inside it),
    # "auto" (dense on CUDA and in a compiled step, tree on CPU)
    nearest: str = "auto"
    # what the geometry features' distance d(p) is: "chamfer" (the release's: nearest sampled point of another
    # object, signed by its normal) | "parts" (signed distance to the other objects' convex parts, exact sign,
    # measured up to 10 cm: spread.model.parts_distance; the batches then carry the part planes)
    geometry_distance: str = "chamfer"
    # each object's own geometric state (its deepest point, shares inside and in contact, where it penetrates and
    # where it touches: spread.model.perceiver.object_summary) added to its node's input (a zero-initialised
    # projection), beside the scene perceiver's tokens; variant "geometry" only
    geometry_summary: bool = False
    # each ordered pair's geometric state (how deep i's deepest point lies in j alone, and j's in i:
    # spread.model.perceiver.pair_features) added to its edge's features (a zero-initialised projection), so the
    # graph attention reads it on the edge it concerns; variant "geometry" with geometry_distance "parts" only
    geometry_pairs: bool = False
    # where the geometry features pose the scene: "x_t" (the release's: the noisy states of the step) | "x0_hat" (the
    # network's own clean estimate, self-conditioning: a first, gradient-free pass at x_t gives x̂_0, clipped to
    # ±1, and the second reads the geometry of the scene posed there — in training and at every sampling step, so
    # a step costs two passes); variant "geometry" only
    geometry_at: str = "x_t"

    @classmethod
    def from_any(cls, config: "Mapping[str, Any] | ModelConfig | None" = None, **overrides) -> "ModelConfig":
        """A config, a mapping of fields (from a Hydra node or a checkpoint), or None (the defaults)."""
        if config is None:
            return replace(cls(), **overrides)
        if isinstance(config, ModelConfig):
            return replace(config, **overrides)
        if isinstance(config, str):
            raise ValueError(f"model config '{config}': give the fields (compose conf/model/{config}.yaml: "
                             f"spread.configs.model_config('{config}'))")
        known = {f.name for f in fields(cls)}
        unknown = set(config) - known
        if unknown:
            raise ValueError(f"ModelConfig: unknown fields {sorted(unknown)}")
        config = dict(config)
        config.setdefault("mount_feature", False)  # a checkpoint saved before the field had no mount code
        return cls(**{**config, **overrides})

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class SceneDiffusionConfig:
    """The arguments of :class:`spread.model.module.SceneDiffusion` (the ``model`` config group's base).

    variant: ``base`` | ``geometry`` (DESIGN §3); config: the network; bounds: translation bounds (None:
    read from ``<data.root>/stats.json`` at setup, then saved in the checkpoint); beta_schedule,
    diffusion_steps: the DDPM training schedule (paper: ``squaredcos_cap_v2``, 1,000); lr, weight_decay: AdamW
    (paper: 1e-4, 1e-4); ema_decay; graph_dropout: > 0 trains classifier-free guidance on the graphs;
    sample_every_n_epochs: > 0 samples val scenes every n epochs and logs val/grecall; val_sampler;
    val_sample_scenes; seed: validation noise.

    Levers for learning at small compute (benchmarks/RESULTS.md, "Learning at small compute": the cpu_hour
    recipe, which levers it uses and which were measured):
    prediction: what the network outputs, ``epsilon`` (the paper's) | ``sample`` (x_0) | ``v_prediction``;
    loss_weighting: ``none`` | ``min_snr`` (with ``min_snr_gamma``); lr_warmup_steps: linear warm-up from 0;
    lr_schedule: ``constant`` | ``cosine`` (from lr after the warm-up down to ``lr_final_ratio``·lr at the
    trainer's ``max_steps``); init_from: a checkpoint whose EMA weights start every matching weight (a
    ``geometry`` model from a trained ``base`` one: the perceiver and the geometry attention start fresh, the
    latter at zero so step 0 predicts what the base model predicts); penetration_weight: λ of the
    penetration-aware term on the decoded poses (:mod:`spread.model.penetration`; 0: off); support_weight: μ
    of the support term (support pairs' rest height and footprint against the training room's, same module);
    spatial_weight: ν of the relation-aware term (:mod:`spread.model.spatial_term`); parts_weight: the weight of
    the parts term (:mod:`spread.model.parts_term`).
    """

    _target_: str = "spread.model.module.SceneDiffusion"
    _convert_: str = "all"
    variant: str = "geometry"
    config: ModelConfig = field(default_factory=ModelConfig)
    bounds: list[float] | None = None
    beta_schedule: str = "squaredcos_cap_v2"
    diffusion_steps: int = 1000
    lr: float = 1e-4
    weight_decay: float = 1e-4
    ema_decay: float = 0.999
    graph_dropout: float = 0.0
    sample_every_n_epochs: int = 0
    val_sampler: str = "ddim-25"
    val_sample_scenes: int = 4
    seed: int = 0
    prediction: str = "epsilon"
    loss_weighting: str = "none"
    min_snr_gamma: float = 5.0
    lr_warmup_steps: int = 0
    lr_schedule: str = "constant"
    lr_final_ratio: float = 0.1
    init_from: str | None = None
    #: λ of the penetration-aware term on the decoded x̂_0 (:mod:`spread.model.penetration`, metres of box overlap
    #: beyond the training scene's, weighted by ᾱ_t); 0 = off (the paper's loss)
    penetration_weight: float = 0.0
    #: μ of the support term (:func:`spread.model.penetration.support_error`: a supported object's rest height
    #: above its supporter and its overhang, metres, against the training room's, weighted by ᾱ_t), added to the
    #: penetration term's. 0 = off
    support_weight: float = 0.0
    #: q of that term's pinball loss on the rest height: a sinking costs 2q, a floating 2(1 − q) (0.5: alike)
    support_quantile: float = 0.5
    #: ν of the relation-aware term (:mod:`spread.model.spatial_term`: how far the decoded boxes are from each pair's
    #: spatial code, metres per ordered pair, beyond the training room's, weighted by ᾱ_t). 0 = off
    spatial_weight: float = 0.0
    #: weight of the parts term (:mod:`spread.model.parts_term`: how deep the decoded objects' surface points lie
    #: inside the other objects' convex parts, metres per object, beyond the training room's, weighted by ᾱ_t; the
    #: batches must carry the part planes: ``data.geometry_distance=parts``). 0 = off
    parts_weight: float = 0.0
    #: torch.compile the training loss (forward and backward of the ε-network; the nearest search stays one
    #: opaque operator). The first steps compile (minutes at paper size); then far fewer launches per step.
    compile: bool = False
    #: torch.compile's mode for it: ``default`` | ``reduce-overhead`` (CUDA graphs: the step replays its kernels
    #: without the host; H200, paper size: +Geometry 0.036 s/step against 0.094 default and 0.149 eager) |
    #: ``max-autotune`` | ``max-autotune-no-cudagraphs``
    compile_mode: str = "default"
    #: a compiled step pads each batch's object count up to a multiple of this (padding objects are masked: the
    #: loss is the same function of the real objects) and compiles one static graph per bucket, at most
    #: ⌈largest room / bucket⌉ of them: rooms of every size from 2 to 51 objects would otherwise recompile the step
    #: for each new count (H200, stop 56: still compiling after 280 s). 1 = no padding (one graph per count)
    compile_bucket: int = 8
