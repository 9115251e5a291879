"""Example plugins for the SPREAD platform, one of each kind a researcher adds most often.

* ``below_floor`` (entry point ``spread.metrics``): the share of objects whose posed convex hull dips more than
  1 cm below the floor plane y = 0 (metres, y up). A :class:`~spread.metrics.base.SceneMetric` with the
  platform's contract: ``evaluate(scene, library)`` → a record with ``to_dict()``, ``accumulate``, ``compute``,
  and ``ratios`` so the bootstrap over scenes gives it an interval.
* ``floor_push`` (``spread.guidance``): a guidance term pushing hull points that are below the floor up,
  Σ relu(−y) per scene; weighed by ``guidance.terms.floor_push``.
* ``jitter_truth`` (``spread.methods``): a "method" that returns each conditioning scene's own poses moved by
  N(0, σ) metres — a sanity baseline that needs no training, only a checkpoint holding its hyper-parameters.
* ``static`` (``spread.physics``): a Stability engine in which nothing moves (``protocol.physics=static``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from lightning import LightningModule

from spread.methods.registry import MethodSpec
from spread.guidance.terms import GuidanceTerm
from spread.metrics.base import SceneMetric, check_scene, ratio
from spread.relations import hull_vertices

BELOW = 0.01  # metres below y = 0 before an object counts


@dataclass
class BelowFloorResult:
    scene_id: str
    num_objects: int
    below: list

    def to_dict(self) -> dict:
        return {"scene_id": self.scene_id, "below_floor": sum(self.below) / self.num_objects,
                "below": [i for i, b in enumerate(self.below) if b]}


class BelowFloorRate(SceneMetric):
    """Objects sunk more than 1 cm below the floor / objects (lower is better)."""

    higher_is_better = False
    column = "Below floor"
    digits = 3
    result_type = BelowFloorResult
    ratios = {"below_floor": ("below", "objects")}

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._add_sum_state("below", dtype=torch.int64)
        self._add_sum_state("objects", dtype=torch.int64)

    def evaluate(self, scene, library) -> BelowFloorResult:
        check_scene(scene, library)
        below = []
        for k, asset in enumerate(scene.asset_id):
            world = hull_vertices(library, str(asset)) @ np.asarray(scene.rotation[k], float).T + scene.translation[k]
            below.append(bool(world[:, 1].min() < -BELOW))
        return BelowFloorResult(scene.scene_id, scene.num_objects, below)

    def accumulate(self, result: BelowFloorResult) -> None:
        self._add("below", sum(result.below))
        self._add("objects", result.num_objects)

    def compute(self) -> torch.Tensor:
        return ratio(self.below, self.objects)


def floor_push(ctx) -> torch.Tensor:
    """Σ relu(−y) over the posed hull points of every real object, per scene (B,)."""
    y = ctx.hull[..., 1]  # (B, N, H) metres
    return (torch.relu(-y) * ctx.mask[..., None]).sum((-1, -2))


FLOOR_PUSH = GuidanceTerm("floor_push", floor_push, description="hull points below the floor pushed up")


class JitterTruth(LightningModule):
    """The conditioning scenes' own poses plus N(0, sigma) metres on x and z (one generator per scene)."""

    def __init__(self, bounds, sigma: float = 0.05, method: str = "jitter_truth"):
        super().__init__()
        self.save_hyperparameters()
        self.register_buffer("bounds", torch.as_tensor(bounds, dtype=torch.float32))

    def sample(self, batch, sampler=None, generator=None, use_ema=True, **kw):
        from spread.model.module import Poses
        from spread.model.poses import poses_from_state

        translation, rotation = poses_from_state(batch["x"].float(), self.bounds)
        B, N, _ = translation.shape
        gens = generator if isinstance(generator, (list, tuple)) else [generator] * B
        noise = torch.stack([torch.randn(N, 3, generator=g) for g in gens]) * self.hparams.sigma
        noise[..., 1] = 0.0
        return Poses(translation + noise * batch["mask"][..., None], rotation)


JITTER_TRUTH = MethodSpec("jitter_truth", JitterTruth, label="Jittered ground truth", sampling="own",
                          graph_conditioned=True, note="ground-truth poses + N(0, σ) on x, z (no training)")


# ---- a physics engine ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class StaticParams:
    """A world in which nothing moves (s): the protocol's plumbing without physics, e.g. to time the rest."""

    time_step: float = 1.0 / 240.0


class StaticWorld:
    """The interface :func:`spread.physics.simulate_runs` drives, with ``step`` a no-op: every object stays where
    it was put, so Stability is 1 for any scene."""

    def __init__(self, params: StaticParams | None = None):
        self.params = params or StaticParams()
        self.time_step = self.params.time_step
        self._poses = None

    def set_time_step(self, dt: float) -> None:
        self.time_step = float(dt)

    def load_scene(self, scene, library) -> None:
        self._poses = (np.asarray(scene.translation, float).copy(), np.asarray(scene.rotation, float).copy())

    def set_poses(self, translation, rotation) -> None:
        self._poses = (np.asarray(translation, float).copy(), np.asarray(rotation, float).copy())

    def step(self, n: int = 1) -> None:
        pass

    def poses(self):
        return self._poses

    def close(self) -> None:
        self._poses = None


def _static_engine():
    from spread.physics.engines import EngineSpec

    return EngineSpec("static", StaticParams, StaticWorld, "nothing moves (protocol plumbing without physics)")


STATIC_ENGINE = _static_engine()
