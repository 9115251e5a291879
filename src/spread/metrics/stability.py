"""Physical stability (DESIGN §6): do the objects stay where the scene puts them under gravity?

Per scene (:func:`scene_stability`): :func:`spread.physics.simulate_runs` simulates
:data:`STABILITY_RUNS` runs of :data:`STABILITY_STEPS` steps of :data:`STABILITY_DT` seconds (pybullet,
static floor at y = 0, every object dynamic with its exact convex parts and its asset's mass), each run
starting from the scene's poses plus a seeded uniform translation jitter of at most
:data:`STABILITY_JITTER` metres per axis. The seed comes from the scene id (:func:`scene_seed`), so a
scene gives the same runs on any worker, in any order.

* **Stability** = share of ordered off-diagonal pairs (i, j) whose spatial code is unchanged after a run.
  Codes before come from the scene's posed meshes (not from the input graph: a generated scene that
  misses its graph is GRecall's business, not stability's); codes after from each run's final poses;
  both by :func:`spread.relations.scene_spatial_codes`. Pooled over runs and pairs.
* **Still objects**: share of (run, object) with the bbox centre displaced < :data:`STILL_DISTANCE` m
  *and* rotated < :data:`STILL_ANGLE` rad from the scene pose; the two shares are also kept apart.

Aggregate (:class:`PhysicsStability`): sums over scenes, so Stability is pair-weighted and the still
shares object-weighted; ``compute()`` returns all four shares (NaN before any pair or object).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from spread.metrics.base import SceneMetric, check_scene, ratio, scene_seed
from spread.metrics.constants import (  # noqa: F401  (re-exported: the protocol's numbers live in constants)
    STABILITY_DT, STABILITY_JITTER, STABILITY_RUNS, STABILITY_STEPS, STILL_ANGLE, STILL_DISTANCE,
)
from spread.metrics.registry import ValueSpec, register_metric
from spread.relations import scene_spatial_codes


@dataclass
class StabilityResult:
    """Stability of one scene. Per-run lists have one entry per run; per-object lists one per object."""

    scene_id: str
    num_objects: int
    seed: int
    pairs: int  # ordered off-diagonal pairs per run, N(N − 1)
    unchanged: list[int] = field(default_factory=list)  # per run: pairs whose code is unchanged
    displacement_ok: list[int] = field(default_factory=list)  # per run: objects moved < STILL_DISTANCE
    rotation_ok: list[int] = field(default_factory=list)  # per run: objects turned < STILL_ANGLE
    still: list[int] = field(default_factory=list)  # per run: objects both
    max_displacement: list[float] = field(default_factory=list)  # per object, over runs, metres
    max_rotation: list[float] = field(default_factory=list)  # per object, over runs, radians

    @property
    def runs(self) -> int:
        return len(self.unchanged)

    @property
    def stability(self) -> float:
        total = self.pairs * self.runs
        return sum(self.unchanged) / total if total else float("nan")

    @property
    def still_fraction(self) -> float:
        total = self.num_objects * self.runs
        return sum(self.still) / total if total else float("nan")

    def to_dict(self) -> dict:
        return {"scene_id": self.scene_id, "stability": self.stability if self.pairs else None,
                "still_fraction": self.still_fraction, "num_objects": self.num_objects, "runs": self.runs,
                "seed": self.seed, "pairs": self.pairs, "unchanged": self.unchanged,
                "displacement_ok": self.displacement_ok, "rotation_ok": self.rotation_ok, "still": self.still,
                "max_displacement": self.max_displacement, "max_rotation": self.max_rotation}


def scene_stability(scene, library, runs: int = STABILITY_RUNS, steps: int = STABILITY_STEPS,
                    dt: float = STABILITY_DT, jitter: float = STABILITY_JITTER, seed: int | None = None,
                    world=None) -> StabilityResult:
    """Stability of one scene (module docstring). ``seed`` defaults to :func:`scene_seed` of the scene id;
    ``world`` to this process's physics world. Raises on a scene that cannot be measured."""
    from spread.physics import displacement_stats, simulate_runs

    check_scene(scene, library)
    seed = scene_seed(scene.scene_id) if seed is None else int(seed)
    ids = [str(a) for a in scene.asset_id]
    n = scene.num_objects
    final = simulate_runs(scene, library, runs=runs, steps=steps, dt=dt, jitter=jitter, seed=seed, world=world)
    before = scene_spatial_codes(scene.translation, scene.rotation, ids, library)
    off = ~np.eye(n, dtype=bool)
    unchanged = [int(((scene_spatial_codes(final.translation[r], final.rotation[r], ids, library) == before)
                      & off).sum()) for r in range(runs)]
    moved = displacement_stats((scene.translation, scene.rotation), (final.translation, final.rotation))
    d_ok = moved.distance < STILL_DISTANCE  # (runs, N)
    a_ok = moved.angle < STILL_ANGLE
    return StabilityResult(
        scene_id=scene.scene_id, num_objects=n, seed=seed, pairs=int(off.sum()), unchanged=unchanged,
        displacement_ok=d_ok.sum(1).tolist(), rotation_ok=a_ok.sum(1).tolist(), still=(d_ok & a_ok).sum(1).tolist(),
        max_displacement=moved.distance.max(0).tolist() if runs else [],
        max_rotation=moved.angle.max(0).tolist() if runs else [],
    )


@register_metric("stability", column="Stability", digits=3, latex=r"Stability$\uparrow$", default=True, order=40,
                 build=lambda p: PhysicsStability(p.stability_runs, p.stability_steps, p.stability_dt,
                                                  p.stability_jitter, base_seed=p.seed, physics=p.physics_params()),
                 description="share of ordered pairs whose spatial code survives the physics runs",
                 extra_values=(ValueSpec("still_fraction", column="Still", digits=3, shown=False, bounds=(0.0, 1.0),
                                         description="share of objects moved < 1 cm and turned < 0.1 rad"),))
class PhysicsStability(SceneMetric):
    """Stability over many scenes (higher is better); protocol constants are the defaults, ``base_seed``
    the evaluation's seed (each scene's runs are seeded by ``scene_seed(scene_id, base_seed)``).

    ``update(scenes, library)`` or ``update(stability_results)``; ``compute()`` → dict of float64 scalar
    tensors: ``stability`` (pair-weighted), ``still_fraction``, ``displacement_ok_fraction``,
    ``rotation_ok_fraction`` (object-weighted).
    """

    higher_is_better = True
    result_type = StabilityResult
    ratios = {"stability": ("unchanged_pairs", "pairs"), "still_fraction": ("still_objects", "objects")}
    reports = ("displacement_ok_fraction", "rotation_ok_fraction")

    def __init__(self, runs: int = STABILITY_RUNS, steps: int = STABILITY_STEPS, dt: float = STABILITY_DT,
                 jitter: float = STABILITY_JITTER, base_seed: int = 0, physics=None, **kwargs):
        super().__init__(**kwargs)
        self.runs, self.steps, self.dt, self.jitter = int(runs), int(steps), float(dt), float(jitter)
        self.physics = physics  # the world's params (engine by type; spread.physics.get_world), None: default
        self.base_seed = int(base_seed)  # the command's seed: a scene's runs use scene_seed(scene_id, base_seed)
        for name in ("unchanged_pairs", "pairs", "objects", "still_objects", "displacement_ok", "rotation_ok"):
            self._add_sum_state(name, dtype=torch.int64)

    def evaluate(self, scene, library) -> StabilityResult:
        from spread.physics import get_world

        world = None if self.physics is None else get_world(self.physics)
        return scene_stability(scene, library, self.runs, self.steps, self.dt, self.jitter,
                               seed=scene_seed(scene.scene_id, self.base_seed), world=world)

    def accumulate(self, result: StabilityResult) -> None:
        self._add("unchanged_pairs", sum(result.unchanged))
        self._add("pairs", result.pairs * result.runs)
        self._add("objects", result.num_objects * result.runs)
        self._add("still_objects", sum(result.still))
        self._add("displacement_ok", sum(result.displacement_ok))
        self._add("rotation_ok", sum(result.rotation_ok))

    def compute(self) -> dict[str, torch.Tensor]:
        return {"stability": ratio(self.unchanged_pairs, self.pairs),
                "still_fraction": ratio(self.still_objects, self.objects),
                "displacement_ok_fraction": ratio(self.displacement_ok, self.objects),
                "rotation_ok_fraction": ratio(self.rotation_ok, self.objects)}
