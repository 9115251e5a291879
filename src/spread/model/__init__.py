"""The SPREAD model: shape tokens, signed chamfer geometry features, geometry perceiver, graph
transformer denoiser, diffusion samplers and the LightningModule (DESIGN §2, paper §3.2–3.3).

Needs only torch, einops, diffusers and lightning; ``SceneDiffusion`` (Lightning) is imported on
first access.
"""

from spread.model.config import ModelConfig  # noqa: F401
from spread.model.diffusion import SAMPLER_KINDS, Sampler, StepContext, training_scheduler  # noqa: F401
from spread.model.ema import EMA  # noqa: F401
from spread.model.geometry import signed_chamfer_features  # noqa: F401
from spread.model.network import VARIANTS, Condition, SceneDenoiser  # noqa: F401
from spread.model.perceiver import GeometryPerceiver  # noqa: F401
from spread.model.poses import pose_points, poses_from_state  # noqa: F401
from spread.model.recall import graph_recall  # noqa: F401
from spread.model.shape_tokens import PointCloudTokenizer, PrecomputedShapeTokens, ShapeEncoder  # noqa: F401


def __getattr__(name: str):
    if name in ("SceneDiffusion", "Poses"):
        from spread.model import module

        return getattr(module, name)
    raise AttributeError(f"module 'spread.model' has no attribute '{name}'")
