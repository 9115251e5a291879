"""The SPREAD model: shape tokens, signed chamfer geometry features, geometry perceiver, graph
transformer denoiser, diffusion samplers and the LightningModule (DESIGN §2, paper §3.2–3.3).

Needs only torch, einops, diffusers and lightning; every name below is imported on first access.
"""

#: Every public name and the module that defines it, imported on first access (PEP 562): ``import
#: spread.model.config`` does not pay for diffusers and Lightning.
_EXPORTS = {
    "spread.model.config": ("ModelConfig",),
    "spread.model.diffusion": ("SAMPLER_KINDS", "Sampler", "StepContext", "training_scheduler"),
    "spread.model.ema": ("EMA",),
    "spread.model.geometry": ("signed_chamfer_features",),
    "spread.model.network": ("VARIANTS", "Condition", "SceneDenoiser"),
    "spread.model.perceiver": ("GeometryPerceiver",),
    "spread.model.poses": ("pose_points", "poses_from_state"),
    "spread.model.recall": ("graph_recall",),
    "spread.model.shape_tokens": ("PointCloudTokenizer", "PrecomputedShapeTokens", "ShapeEncoder"),
    "spread.model.module": ("SceneDiffusion", "Poses"),
}
_MODULE_OF = {name: module for module, names in _EXPORTS.items() for name in names}


def __getattr__(name: str):
    module = _MODULE_OF.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # looked up once
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_MODULE_OF})
