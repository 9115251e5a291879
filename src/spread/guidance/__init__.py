"""Differentiable guidance for scene sampling (paper §3.4, reference notes §3.2–3.5).

Three terms on posed meshes, each differentiable in torch w.r.t. the normalised states (translation
+ rot6d), CPU or GPU, no compiled extension:

* collision G_C (:mod:`~spread.guidance.collision`): python-fcl BVH triangle pairs between different
  objects, conical distance field penalty both ways, supporters not pushed by what they support;
* gravity G_H (:mod:`~spread.guidance.gravity`): vertical gap from each object's mesh down to its
  supporter's mesh or the floor, outside [ε, ε + θ_H];
* relation G_R (:mod:`~spread.guidance.relation`): supported vertices outside the supporter's xz hull.

:class:`SceneGuidance` (:mod:`~spread.guidance.guide`) combines them with the weights and schedule of a
:class:`GuidanceConfig` (:mod:`~spread.guidance.config`), as the paper's per-step hook (``paper``) or
the release's post-hoc refinement at t = 0 (``refine``); the sampling pipeline
(:class:`spread.sampling.ScenePipeline`) plugs either in as a callback. Imports go guidance → model, never back.
"""

from spread.guidance.config import MODES, GuidanceConfig  # noqa: F401


def __getattr__(name: str):
    if name == "SceneGuidance":  # torch and the model's samplers load with it, not with the config
        from spread.guidance.guide import SceneGuidance

        return SceneGuidance
    raise AttributeError(f"module 'spread.guidance' has no attribute '{name}'")
