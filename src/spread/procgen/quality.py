"""Ground-truth grade of a generated room, measured independently of the generator's own geometry.

The generator annotates with the convex-parts distance proxy of :mod:`spread.relations`; these checks
use exact mesh distances (trimesh signed distance on the watertight visual meshes), FCL candidate
pairs (trimesh ``CollisionManager``), and a fresh physics re-simulation. Thresholds are the issue's:

* no object pair penetrates deeper than :data:`MAX_PENETRATION` (1 cm);
* every small object has exactly one supporter, at a support distance under :data:`MAX_SUPPORT_DISTANCE`
  (2 mm; |min signed distance| of its vertices and surface samples to the supporter's mesh);
* re-simulating 100 steps of 1/60 s moves at least 98% of objects less than 1 cm;
* the support graph is a forest rooted at floor-standing furniture.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

MAX_PENETRATION = 0.01
MAX_SUPPORT_DISTANCE = 0.002
RESIM_MOTION = 0.01
RESIM_STILL_SHARE = 0.98
FLOOR_TOLERANCE = 0.002


@dataclass
class RoomQuality:
    scene_id: str
    num_objects: int
    max_penetration: float
    support_distances: list[float] = field(default_factory=list)
    objects_without_one_supporter: list[int] = field(default_factory=list)
    forest_errors: list[str] = field(default_factory=list)
    resim_moved: int = 0

    @property
    def max_support_distance(self) -> float:
        return max(self.support_distances, default=0.0)

    @property
    def resim_still_share(self) -> float:
        return 1.0 - self.resim_moved / max(self.num_objects, 1)

    def failures(self) -> list[str]:
        out = []
        if self.max_penetration >= MAX_PENETRATION:
            out.append(f"penetration {self.max_penetration:.4f} m")
        if self.max_support_distance >= MAX_SUPPORT_DISTANCE:
            out.append(f"support distance {self.max_support_distance:.4f} m")
        if self.objects_without_one_supporter:
            out.append(f"objects without exactly one supporter: {self.objects_without_one_supporter}")
        out.extend(self.forest_errors)
        if self.resim_still_share < RESIM_STILL_SHARE:
            out.append(f"re-simulation moved {self.resim_moved}/{self.num_objects} objects ≥ 1 cm")
        return out

    def to_dict(self) -> dict:
        d = asdict(self)
        d.update(max_support_distance=self.max_support_distance, resim_still_share=self.resim_still_share,
                 failures=self.failures())
        return d


def posed_mesh(library, scene, i: int):
    mesh = library.mesh(str(scene.asset_id[i])).copy()
    T = np.eye(4)
    T[:3, :3] = scene.rotation[i]
    T[:3, 3] = scene.translation[i]
    return mesh.apply_transform(T)


def outside_distance(mesh, points: np.ndarray) -> np.ndarray:
    """Exact signed distance of points to a watertight mesh, metres, positive OUTSIDE
    (trimesh's own sign is positive inside)."""
    import trimesh

    with np.errstate(divide="ignore", invalid="ignore"):  # trimesh's barycentrics on sliver triangles
        return -trimesh.proximity.signed_distance(mesh, points)


def _samples(mesh, n: int, seed: int) -> np.ndarray:
    return np.concatenate([np.asarray(mesh.vertices), np.asarray(mesh.sample(n, seed=seed))])


def check_room(scene, library, resimulate: bool = True, samples: int = 400) -> RoomQuality:
    """Measure one room against the ground-truth thresholds (see the module docstring)."""
    import trimesh

    n = scene.num_objects
    meshes = [posed_mesh(library, scene, i) for i in range(n)]
    manager = trimesh.collision.CollisionManager()
    for i, m in enumerate(meshes):
        manager.add_object(str(i), m)
    _, pairs = manager.in_collision_internal(return_names=True)
    worst = 0.0
    for a, b in pairs:
        i, j = int(a), int(b)
        for src, dst in ((i, j), (j, i)):
            worst = max(worst, float(-outside_distance(meshes[dst], _samples(meshes[src], samples, 0)).min()))
    quality = RoomQuality(scene.scene_id, n, max(worst, 0.0))

    sup = scene.physical == 1
    roles = [library[str(a)].role for a in scene.asset_id]
    for j in range(n):
        supporters = np.nonzero(sup[:, j])[0]
        if roles[j] == "object" and len(supporters) != 1:
            quality.objects_without_one_supporter.append(j)
        for i in supporters:
            d = outside_distance(meshes[i], _samples(meshes[j], samples, 1))
            quality.support_distances.append(float(abs(d.min())))
        # follow supporters down to the root: no cycle, root is furniture on the floor
        seen, k = set(), j
        while sup[:, k].any():
            if k in seen:
                quality.forest_errors.append(f"support cycle through object {k}")
                break
            seen.add(k)
            k = int(np.argmax(sup[:, k]))
        else:
            if roles[k] != "furniture":
                quality.forest_errors.append(f"object {j}'s support chain ends at {scene.category[k]} (not furniture)")
            elif abs(float(meshes[k].vertices[:, 1].min())) > FLOOR_TOLERANCE:
                quality.forest_errors.append(f"root {k} ({scene.category[k]}) is not on the floor")
    if resimulate:
        from spread.physics import simulate_runs

        runs = simulate_runs(scene, library, runs=1, steps=100, dt=1 / 60, jitter=0.0, seed=0)
        moved = np.linalg.norm(runs.translation[0] - scene.translation, axis=1) >= RESIM_MOTION
        quality.resim_moved = int(moved.sum())
    return quality
