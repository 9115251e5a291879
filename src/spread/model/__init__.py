"""The SPREAD model: shape tokens, signed chamfer geometry features, geometry perceiver, graph
transformer denoiser, diffusion samplers and the LightningModule (DESIGN §2, paper §3.2–3.3).

Needs only torch, einops, diffusers and lightning; every name below is imported on first access.
"""

from spread.lazy import lazy_names

#: Every public name and the module that defines it, imported on first access (PEP 562): ``import
#: spread.model.config`` does not pay for diffusers and Lightning.
_EXPORTS = {
    "spread.model.config": ("ModelConfig",),
    "spread.model.diffusion": ("StepContext",),
    "spread.model.sampler": ("SAMPLER_KINDS", "Sampler", "TRAIN_SCHEDULER_CONFIG", "training_scheduler"),
    "spread.model.ema": ("EMA",),
    "spread.model.geometry": ("signed_chamfer_features",),
    "spread.model.network": ("VARIANTS", "Condition", "SceneDenoiser"),
    "spread.model.perceiver": ("GeometryPerceiver",),
    "spread.model.poses": ("pose_points", "poses_from_state"),
    "spread.model.recall": ("graph_recall",),
    "spread.model.shape_tokens": ("PointCloudTokenizer", "PrecomputedShapeTokens", "ShapeEncoder"),
    "spread.model.module": ("SceneDiffusion", "Poses"),
}
__getattr__, __dir__ = lazy_names(__name__, _EXPORTS)
