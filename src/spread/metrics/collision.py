"""Col_mesh (DESIGN §6): the share of objects in at least one significant mesh collision.

Per scene (:func:`scene_collisions`):

1. **Candidate pairs.** Pairs whose posed world AABBs overlap are tested with python-fcl on the posed
   canonical meshes (``fcl.Convex`` for convex meshes, ``fcl.BVHModel`` otherwise — the geometry
   ``trimesh.collision.CollisionManager`` builds). FCL's mesh–mesh test only finds intersecting
   surfaces, so a mesh entirely inside another is missed; every pair whose AABB contains the other's
   AABB (a necessary condition for containment) is therefore a candidate too. A mesh with openings
   (not watertight, measured as a winding-number solid, :mod:`spread.metrics.solid`) can be entered
   through an opening without crossing a face, so a pair with such a mesh is a candidate as soon as
   their AABBs overlap.
   We call ``fcl.collide`` per pair rather than going through ``CollisionManager``: the manager rebuilds
   each object's BVH on every ``add_object`` (≈ 20 ms for a 5k-face mesh) and identifies objects by their
   geometry, so geometry cannot be shared; here each asset's FCL geometry is built once per process.
2. **Depth.** For a candidate pair (a, b): a's vertices and surface samples are moved into b's frame,
   their signed distances to b's watertight mesh computed (trimesh, made positive outside), and
   depth(a→b) = max(0, −min). The pair's depth is the deeper of the two directions. A point deep
   inside the other mesh counts, so containment counts: a small box inside a big one has a depth at
   least its distance to the big box's surface. Where the surface gives no depth above the threshold,
   a's interior samples (its surface samples moved inward) count once deeper than it: two objects of one
   shape that coincide, or nearly, collide (their surfaces lie on each other, their interiors inside).
   (:func:`spread.metrics.geometry.min_signed_distance` gives the exact minimum over the point set and
   skips points that cannot be deeper.)
3. An object **collides** when one of its pairs is deeper than :data:`COLLISION_DEPTH_THRESHOLD`.

Aggregate (:class:`MeshCollisionRate`): colliding objects / objects over all scenes (object-weighted,
"over the test set" as the protocol says), NaN before any object was seen.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from spread.metrics.base import SceneMetric, check_scene, ratio
from spread.metrics.constants import COLLISION_DEPTH_THRESHOLD
from spread.metrics.registry import register_metric
from spread.metrics.geometry import (asset_geometry, fcl_geometry, interior_points, min_signed_distance, to_local,
                                     to_world)
from spread.relations import scene_aabbs



@dataclass
class PairDepth:
    """One candidate pair (i < j): penetration depth (metres, ≥ 0), and why it was a candidate."""

    i: int
    j: int
    depth: float
    fcl_contact: bool  # FCL found intersecting surfaces
    contained: bool  # one AABB contains the other

    def to_dict(self) -> dict:
        return {"i": self.i, "j": self.j, "depth": self.depth, "fcl_contact": self.fcl_contact,
                "contained": self.contained}


@dataclass
class CollisionResult:
    """Col_mesh of one scene: which objects collide significantly, and every candidate pair's depth."""

    scene_id: str
    num_objects: int
    colliding: list[bool]  # (N,) object in at least one pair deeper than the threshold
    pairs: list[PairDepth] = field(default_factory=list)
    threshold: float = COLLISION_DEPTH_THRESHOLD

    @property
    def num_colliding(self) -> int:
        return int(sum(self.colliding))

    @property
    def rate(self) -> float:
        return self.num_colliding / self.num_objects if self.num_objects else float("nan")

    def to_dict(self) -> dict:
        return {"scene_id": self.scene_id, "col_mesh": self.rate, "num_objects": self.num_objects,
                "num_colliding": self.num_colliding, "threshold": self.threshold,
                "colliding": [i for i, c in enumerate(self.colliding) if c],
                "pairs": [p.to_dict() for p in self.pairs]}


def candidate_pairs(scene, library) -> list[tuple[int, int, bool, bool]]:
    """(i, j, fcl_contact, contained) for every pair i < j that FCL finds touching, whose AABBs nest, or
    whose AABBs overlap when one of the two meshes has openings."""
    import fcl

    ids = [str(a) for a in scene.asset_id]
    T = scene.translation.astype(np.float64)
    R = scene.rotation.astype(np.float64)
    lo, hi = scene_aabbs(T, R, ids, library)
    overlap = np.all((lo[:, None] <= hi[None]) & (hi[:, None] >= lo[None]), axis=-1)
    inside = np.all((lo[:, None] >= lo[None]) & (hi[:, None] <= hi[None]), axis=-1)  # [i, j]: i's box in j's
    nested = inside | inside.T
    openings = np.array([asset_geometry(library, a).has_openings for a in ids])
    enterable = openings[:, None] | openings[None, :]
    objects: dict[int, object] = {}

    def obj(k: int):
        if k not in objects:
            objects[k] = fcl.CollisionObject(fcl_geometry(library, ids[k]), fcl.Transform(R[k], T[k]))
        return objects[k]

    out = []
    for i, j in zip(*np.nonzero(np.triu(overlap, 1))):
        i, j = int(i), int(j)
        result = fcl.CollisionResult()
        fcl.collide(obj(i), obj(j), fcl.CollisionRequest(), result)
        touching = bool(result.is_collision)
        if touching or nested[i, j] or enterable[i, j]:
            out.append((i, j, bool(touching), bool(nested[i, j])))
    return out


def penetration_depth(scene, library, a: int, b: int, threshold: float = COLLISION_DEPTH_THRESHOLD) -> float:
    """Depth (metres, ≥ 0) of object a's points inside object b's mesh: max(0, −min signed distance) over a's
    surface points; where that is not above ``threshold``, a's interior points (:func:`~spread.metrics.geometry.
    interior_points`) count too, once deeper than it (only points more than ``threshold`` inside b's box are
    queried: a resting pair's interior stays unqueried)."""
    ga = asset_geometry(library, str(scene.asset_id[a]))
    gb = asset_geometry(library, str(scene.asset_id[b]))
    Ra, ta = scene.rotation[a].astype(np.float64), scene.translation[a].astype(np.float64)
    Rb, tb = scene.rotation[b].astype(np.float64), scene.translation[b].astype(np.float64)
    local = to_local(to_world(ga.points, Ra, ta), Rb, tb)
    d, _ = min_signed_distance(gb, local, stop_at=0.0)
    depth = max(0.0, -d)
    if depth <= threshold:  # coincident or nearly: the surface lies on b's surface, the interior inside it
        inner = to_local(to_world(interior_points(library, str(scene.asset_id[a])), Ra, ta), Rb, tb)
        d, _ = min_signed_distance(gb, inner, stop_at=-threshold)
        if -d > threshold:
            depth = -d
    return depth


def scene_collisions(scene, library, threshold: float = COLLISION_DEPTH_THRESHOLD) -> CollisionResult:
    """Col_mesh of one scene (module docstring); raises on a scene that cannot be measured."""
    check_scene(scene, library)
    n = scene.num_objects
    colliding = np.zeros(n, bool)
    pairs = []
    for i, j, touching, contained in candidate_pairs(scene, library):
        depth = max(penetration_depth(scene, library, i, j, threshold),
                    penetration_depth(scene, library, j, i, threshold))
        pairs.append(PairDepth(i, j, depth, touching, contained))
        if depth > threshold:
            colliding[[i, j]] = True
    return CollisionResult(scene.scene_id, n, colliding.tolist(), pairs, float(threshold))


@register_metric("col_mesh", column="Col_mesh", digits=3, latex=r"Col$_{\text{mesh}}\downarrow$", default=True,
                 order=20, build=lambda protocol: MeshCollisionRate(protocol.collision_threshold),
                 description="share of objects in at least one collision deeper than the threshold")
class MeshCollisionRate(SceneMetric):
    """Col_mesh over many scenes: colliding objects / all objects (lower is better).

    ``update(scenes, library)`` or ``update(collision_results)``; ``compute()`` → float64 scalar tensor
    (NaN before any object).
    """

    higher_is_better = False
    result_type = CollisionResult
    ratios = {"col_mesh": ("colliding_objects", "objects")}
    counts = {"n_colliding_objects": "colliding_objects"}

    def __init__(self, threshold: float = COLLISION_DEPTH_THRESHOLD, **kwargs):
        super().__init__(**kwargs)
        self.threshold = float(threshold)
        self._add_sum_state("colliding_objects", dtype=torch.int64)
        self._add_sum_state("objects", dtype=torch.int64)

    def evaluate(self, scene, library) -> CollisionResult:
        return scene_collisions(scene, library, self.threshold)

    def accumulate(self, result: CollisionResult) -> None:
        if result.threshold != self.threshold:
            raise ValueError(f"scene '{result.scene_id}' was measured with threshold {result.threshold} m, "
                             f"this metric uses {self.threshold} m")
        self._add("colliding_objects", result.num_colliding)
        self._add("objects", result.num_objects)

    def compute(self) -> torch.Tensor:
        return ratio(self.colliding_objects, self.objects)
