"""Physics settling and repair: drop the placed objects in pybullet, remove what went wrong, snap
contacts exactly, and keep only rooms that stay put when simulated again.

Pipeline for one room (all in metres, world frame):

1. **Settle**: every object dynamic, simulate until at rest (``PhysicsWorld.settle``).
2. **Reject** small objects that fell to the floor or have no supporter, slid more than
   ``max_slide`` from where they were put, tipped more than ``max_tilt`` radians, or interpenetrate
   another object deeper than ``max_penetration``; pieces of furniture that moved or tilted likewise.
   A rejected object takes everything resting on it along. Re-settle what is left; repeat.
3. **Snap**: going up the support forest from the floor, move each object vertically so that its
   lowest downward-facing samples touch its supporter (floor: y = 0) exactly: support distances
   become ≈ 0 instead of the solver's resting penetration.
4. **Verify**: simulate ``verify_steps`` of 1/60 s (the evaluation's protocol) in ``verify_physics``
   (pybullet, or MuJoCo for rooms meant to be measured with ``protocol.physics=mujoco``); objects that
   move more than ``verify_motion`` are rejected and the room goes back to step 1 (bounded by ``rounds``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spread.relations import physical_codes
from spread.scene import Scene


@dataclass
class SettleConfig:
    max_steps: int = 1200
    #: at rest: every object slower than these for ``patience`` steps (light objects on a soft-looking
    #: stack jitter at ~0.07 rad/s without drifting; the verify run catches real motion)
    rest_linear_speed: float = 0.005
    rest_angular_speed: float = 0.15
    max_slide: float = 0.05
    max_tilt: float = 0.35
    max_penetration: float = 0.004
    furniture_max_motion: float = 0.02
    verify_steps: int = 100
    verify_dt: float = 1.0 / 60.0
    verify_motion: float = 0.005
    rounds: int = 4
    #: engine of the verification run: "pybullet" (the settling world itself) or "mujoco"
    verify_physics: str = "pybullet"

    def __post_init__(self) -> None:
        if self.verify_physics not in ("pybullet", "mujoco"):
            raise ValueError(f"settle.verify_physics must be 'pybullet' or 'mujoco', got {self.verify_physics!r}")


@dataclass
class SettleReport:
    rounds: int = 0
    removed: dict[str, int] = field(default_factory=dict)
    steps: int = 0

    def count(self, reason: str, n: int = 1) -> None:
        self.removed[reason] = self.removed.get(reason, 0) + n


def rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angle (radians) of Ra⁻¹·Rb for stacks (..., 3, 3)."""
    tr = np.einsum("...ji,...ji->...", Ra, Rb)
    return np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0))


def _bare_scene(ids, categories, T, R) -> Scene:
    n = len(ids)
    spatial = np.zeros((n, n), np.int8)
    np.fill_diagonal(spatial, 6)
    return Scene("settling", np.asarray(ids), np.asarray(categories), T, R, spatial, np.zeros((n, n), np.int8))


def _descendants(roots: set[int], parent: np.ndarray, codes: np.ndarray) -> set[int]:
    """Everything resting on ``roots``, by intended parent or by detected support."""
    out = set(roots)
    changed = True
    while changed:
        changed = False
        for j in range(len(parent)):
            if j in out:
                continue
            if (parent[j] >= 0 and parent[j] in out) or any(codes[i, j] == 1 for i in out):
                out.add(j)
                changed = True
    return out


def settle_room(ids: list[str], categories: list[str], roles: list[str], parent: list[int | None],
                translation: np.ndarray, rotation: np.ndarray, library, config: SettleConfig | None = None,
                world=None):
    """Settle one room. Returns ``(keep (K,) indices into the input, translation (K, 3), rotation (K, 3, 3),
    PhysicalRelations of the kept objects, SettleReport)``; K may be 0."""
    from spread.physics import PhysicsWorld

    config = config or SettleConfig()
    report = SettleReport()
    own_world = world is None
    world = world or PhysicsWorld()
    try:
        return _settle(ids, categories, roles, parent, translation, rotation, library, config, world, report)
    finally:
        if own_world:
            world.close()


def _mujoco_world():
    """This process's MuJoCo world for verification runs (default :class:`~spread.physics.MujocoParams`)."""
    global _MUJOCO
    if _MUJOCO is None:
        from spread.physics import MujocoWorld

        _MUJOCO = MujocoWorld()
    return _MUJOCO


_MUJOCO = None


def _settle(ids, categories, roles, parent, translation, rotation, library, config, world, report):
    from spread.physics import simulate_runs

    n = len(ids)
    alive = np.arange(n)
    parent_arr = np.array([-1 if p is None else p for p in parent])
    T0 = np.asarray(translation, np.float64).copy()
    R0 = np.asarray(rotation, np.float64).copy()
    T, R = T0.copy(), R0.copy()
    furniture = np.array([r == "furniture" for r in roles])
    rel = None
    for _round in range(config.rounds):
        report.rounds += 1
        ids_a = [ids[k] for k in alive]
        world.load_scene(_bare_scene(ids_a, [categories[k] for k in alive], T[alive], R[alive]), library)
        result = world.settle(max_steps=config.max_steps, linear_tol=config.rest_linear_speed,
                              angular_tol=config.rest_angular_speed)
        report.steps += int(result.steps)
        Ta, Ra = result.translation, result.rotation
        rel = physical_codes(Ta, Ra, ids_a, library)
        bad = _find_bad(alive, Ta, Ra, T0, R0, rel, furniture, config, report, library, ids_a)
        if not bad:
            T[alive], R[alive] = Ta, Ra
            Ts, rel = _snap(Ta, Ra, rel, ids_a, library)
            # verify with the evaluation protocol
            runs = simulate_runs(_bare_scene(ids_a, [categories[k] for k in alive], Ts, Ra), library, runs=1,
                                 steps=config.verify_steps, dt=config.verify_dt, jitter=0.0, seed=0,
                                 world=world if config.verify_physics == "pybullet" else _mujoco_world())
            motion = np.linalg.norm(runs.translation[0] - Ts, axis=1)
            movers = {int(k) for k in np.nonzero(motion > config.verify_motion)[0]}
            if not movers:
                return alive, Ts, Ra, rel, report
            report.count("moved_on_verify", len(movers))
            bad = movers
            Ta = Ts
        drop = _descendants(bad, _local_parents(parent_arr, alive), rel.codes)
        keep_local = np.array([k for k in range(len(alive)) if k not in drop], int)
        T[alive], R[alive] = Ta, Ra
        alive = alive[keep_local]
        if len(alive) == 0:
            break
    return alive[:0], T[:0], R[:0], None, report


def _local_parents(parent_arr: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """Intended parents re-indexed into the ``alive`` subset (−1 when the parent is gone or the floor)."""
    pos = {int(g): k for k, g in enumerate(alive)}
    return np.array([pos.get(int(parent_arr[g]), -1) for g in alive])


def _find_bad(alive, Ta, Ra, T0, R0, rel, furniture, config, report, library, ids_a) -> set[int]:
    bad: set[int] = set()
    slide = np.linalg.norm((Ta - T0[alive])[:, [0, 2]], axis=1)
    tilt = rotation_angle(R0[alive], Ra)
    has_supporter = (rel.codes == 1).any(axis=0)
    for k, g in enumerate(alive):
        if furniture[g]:
            if slide[k] > config.furniture_max_motion or tilt[k] > config.max_tilt or not rel.floor_supported[k]:
                bad.add(k)
                report.count("furniture_moved")
            continue
        if rel.floor_supported[k] or not has_supporter[k]:
            bad.add(k)
            report.count("fell_or_unsupported")
        elif slide[k] > config.max_slide:
            bad.add(k)
            report.count("slid")
        elif tilt[k] > config.max_tilt:
            bad.add(k)
            report.count("tipped")
    depth = -np.minimum(rel.min_distance, rel.min_distance.T)
    for i, j in zip(*np.nonzero(np.triu(depth > config.max_penetration, 1))):
        if i in bad or j in bad:
            continue
        vi, vj = library[ids_a[i]].volume, library[ids_a[j]].volume
        loser = int(i if (vi < vj and not furniture[alive[i]]) or furniture[alive[j]] else j)
        if furniture[alive[loser]]:
            continue
        bad.add(loser)
        report.count("penetration")
    return bad


def _snap(T: np.ndarray, R: np.ndarray, rel, ids, library):
    """Move objects vertically, from the floor up, so each touches its supporter exactly."""
    from spread.relations import asset_planes, posed_planes, signed_distance_to_parts, DOWNWARD_NORMAL_Y

    T = T.copy()
    n = len(ids)
    supporter = np.full(n, -1)
    for i, j in zip(*np.nonzero(rel.codes == 1)):
        supporter[j] = i
    order, seen = [], set()

    def visit(j: int) -> None:
        if j in seen:
            return
        seen.add(j)
        if supporter[j] >= 0:
            visit(int(supporter[j]))
        order.append(j)

    for j in range(n):
        visit(j)
    for j in order:
        pts, nrm = library.surface_points(ids[j])
        world_pts = pts.astype(np.float64) @ R[j].T + T[j]
        down = (nrm.astype(np.float64) @ R[j].T)[:, 1] < DOWNWARD_NORMAL_Y
        if supporter[j] < 0:
            gap = world_pts[:, 1].min()
        else:
            i = int(supporter[j])
            planes = posed_planes(asset_planes(library, ids[i]), R[i], T[i])
            d = signed_distance_to_parts(world_pts[down], *planes)
            # the lowest contact: samples over the supporter (within 2 cm) decide the gap
            close = d[d < 0.02]
            gap = close.min() if close.size else 0.0
        T[j, 1] -= gap
    rel = physical_codes(T, R, ids, library)
    return T, rel
