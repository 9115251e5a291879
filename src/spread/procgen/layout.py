"""Furniture on the floor: against walls, free-standing, or beside another piece; never overlapping.

Furniture yaw is a multiple of 90°, so footprints are axis-aligned rectangles and the overlap test is
exact. An asset's front is its local +z: a piece against the wall at z = −d/2 has yaw 0 and faces +z.
"""

from __future__ import annotations

import math

import numpy as np

from spread.procgen.placement import Placement, footprint, yaw_matrix
from spread.procgen.room_types import RoomConfig, RoomType

#: yaw that turns an asset's front (+z) away from each wall: back wall (−z), front wall (+z), −x, +x
WALL_YAWS = {"-z": 0.0, "+z": math.pi, "-x": math.pi / 2, "+x": -math.pi / 2}


def _rect(fp) -> np.ndarray:
    x0, z0, x1, z1 = fp.bounds
    return np.array([x0, z0, x1, z1])


def _overlaps(rect: np.ndarray, rects: list[np.ndarray], gap: float) -> bool:
    for r in rects:
        if rect[0] < r[2] + gap and r[0] < rect[2] + gap and rect[1] < r[3] + gap and r[1] < rect[3] + gap:
            return True
    return False


def place_furniture(room: RoomType, width: float, depth: float, library, rng: np.random.Generator,
                    config: RoomConfig, hulls: dict[str, np.ndarray], tries: int = 60) -> list[Placement]:
    """Place the room type's furniture on the floor ``[−w/2, w/2] × [−d/2, d/2]``; returns placements.

    Pieces that find no free spot after ``tries`` attempts are skipped (a crowded room simply has
    fewer of them). ``hulls`` maps asset id → canonical hull vertices.
    """
    placed: list[Placement] = []
    rects: list[np.ndarray] = []
    half = np.array([width / 2, depth / 2])
    for slot in room.furniture:
        ids = library.ids_of(slot.category)
        if not ids:
            continue
        count = int(rng.integers(slot.count[0], slot.count[1] + 1))
        for _ in range(count):
            asset_id = ids[int(rng.integers(len(ids)))]
            rec = library[asset_id]
            rest = next((p for p in rec.rest_poses if p.name == "upright"), rec.rest_poses[0])
            for _attempt in range(tries):
                yaw, xz = _propose(slot.place, rec.extents, rest.rotation, half, placed, rng, config)
                if yaw is None:
                    break
                R = yaw_matrix(yaw) @ rest.rotation
                t = np.array([xz[0], rest.bottom_offset + config.drop_height, xz[1]])
                rect = _rect(footprint(hulls[asset_id], R, t))
                inside = (rect[0] >= -half[0] + config.wall_gap - 1e-9 and rect[2] <= half[0] - config.wall_gap + 1e-9
                          and rect[1] >= -half[1] + config.wall_gap - 1e-9 and rect[3] <= half[1] - config.wall_gap + 1e-9)
                if inside and not _overlaps(rect, rects, config.furniture_gap):
                    placed.append(Placement(asset_id, rec.category, rec.role, R, t, parent=None, rest=rest.name,
                                            extents=np.asarray(rec.extents, float)))
                    rects.append(rect)
                    break
    return placed


def _propose(place: str, extents, rest_rotation, half: np.ndarray, placed: list[Placement],
             rng: np.random.Generator, config: RoomConfig):
    """A candidate (yaw, xz centre) for one piece by its placement rule."""
    ext = np.abs(rest_rotation) @ np.asarray(extents)  # extents after the rest pose, x y z
    if place.startswith("near:"):
        anchors = [p for p in placed if p.category == place[5:]]
        if anchors:
            return _beside(anchors[int(rng.integers(len(anchors)))], ext, rng, config)
        place = "any"
    if place == "wall":
        wall = ("-z", "+z", "-x", "+x")[int(rng.integers(4))]
        yaw = WALL_YAWS[wall]
        along_x = wall in ("-z", "+z")
        # after the yaw, the piece's local x runs along the wall and local z away from it
        w_along, w_depth = ext[0], ext[2]
        span = (half[0] if along_x else half[1]) - w_along / 2 - config.wall_gap
        if span < 0:
            return 0.0, np.array([1e9, 1e9])
        s = rng.uniform(-span, span)
        off = (half[1] if along_x else half[0]) - w_depth / 2 - config.wall_gap
        if wall == "-z":
            return yaw, np.array([s, -off])
        if wall == "+z":
            return yaw, np.array([s, off])
        if wall == "-x":
            return yaw, np.array([-off, s])
        return yaw, np.array([off, s])
    yaw = float(rng.integers(4)) * math.pi / 2
    if place == "centre":
        return yaw, rng.uniform(-0.3, 0.3, size=2) * half
    return yaw, rng.uniform(-1, 1, size=2) * half


def _beside(anchor: Placement, ext: np.ndarray, rng: np.random.Generator, config: RoomConfig):
    """Next to ``anchor`` on one of its four sides, facing it (chairs at a table, nightstand by a bed)."""
    ax = anchor.rotation[:, 0]
    az = anchor.rotation[:, 2]
    a_half_x = anchor.half_extent_along(ax)
    a_half_z = anchor.half_extent_along(az)
    side = int(rng.integers(4))
    gap = config.furniture_gap + rng.uniform(0.0, 0.1)
    if side in (0, 1):  # left/right of the anchor, along its x axis
        sign = 1 if side == 0 else -1
        centre = anchor.translation[[0, 2]] + sign * (a_half_x + gap + ext[2] / 2) * ax[[0, 2]]
        centre += rng.uniform(-0.5, 0.5) * a_half_z * az[[0, 2]]
        facing = -sign * ax
    else:  # in front of / behind the anchor, along its z axis
        sign = 1 if side == 2 else -1
        centre = anchor.translation[[0, 2]] + sign * (a_half_z + gap + ext[2] / 2) * az[[0, 2]]
        centre += rng.uniform(-0.5, 0.5) * a_half_x * ax[[0, 2]]
        facing = -sign * az
    yaw = math.atan2(facing[0], facing[2])  # local +z turned to face the anchor
    return yaw, centre
