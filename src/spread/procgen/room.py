"""One room end to end: type and size → furniture → small objects → physics settling → annotated Scene."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spread.procgen.layout import place_furniture
from spread.procgen.populate import populate
from spread.procgen.room_types import ROOM_TYPES, RoomConfig
from spread.procgen.settle import SettleConfig, SettleReport, settle_room
from spread.relations import hull_vertices, scene_spatial_codes
from spread.scene import Scene

#: Room height written into ``Scene.room`` (metres); rooms are open boxes, walls carry no objects.
ROOM_HEIGHT = 2.8


@dataclass
class RoomResult:
    scene: Scene | None
    room_type: str
    placed: int
    report: SettleReport
    attempt: int


class HullCache:
    """asset id → canonical convex-hull vertices: a view of the one cache in
    :func:`spread.relations.hull_vertices` bound to a library."""

    def __init__(self, library):
        self.library = library

    def __getitem__(self, asset_id: str) -> np.ndarray:
        return hull_vertices(self.library, asset_id)


def generate_room(scene_id: str, rng: np.random.Generator, library, room_config: RoomConfig,
                  settle_config: SettleConfig, hulls: HullCache | None = None, world=None) -> RoomResult:
    """Generate, settle and annotate one room. ``scene`` is None when fewer than
    ``room_config.min_objects`` objects survive settling."""
    hulls = hulls if hulls is not None else HullCache(library)
    names = sorted(t for t, w in room_config.room_types.items() if w > 0 and t in ROOM_TYPES)
    if not names:
        raise ValueError(f"room.room_types has no known room type with positive weight (known: {sorted(ROOM_TYPES)})")
    weights = np.array([room_config.room_types[t] for t in names], float)
    room_type = ROOM_TYPES[names[int(rng.choice(len(names), p=weights / weights.sum()))]]
    width = float(rng.uniform(*room_type.width))
    depth = float(rng.uniform(*room_type.depth))
    max_objects = int(rng.integers(max(room_config.min_objects, 2), room_config.max_objects + 1))
    placements = place_furniture(room_type, width, depth, library, rng, room_config, hulls)
    placements = populate(placements, library, rng, room_config, hulls, max_objects=max_objects)
    ids = [p.asset_id for p in placements]
    keep, T, R, rel, report = settle_room(
        ids, [p.category for p in placements], [p.role for p in placements], [p.parent for p in placements],
        np.array([p.translation for p in placements]).reshape(-1, 3),
        np.array([p.rotation for p in placements]).reshape(-1, 3, 3),
        library, settle_config, world=world,
    )
    if len(keep) < room_config.min_objects or rel is None:
        return RoomResult(None, room_type.name, len(placements), report, 0)
    kept_ids = [ids[k] for k in keep]
    spatial = scene_spatial_codes(T, R, kept_ids, library)
    room = np.array([[-width / 2, 0.0, -depth / 2], [width / 2, ROOM_HEIGHT, depth / 2]], np.float32)
    scene = Scene(
        scene_id=scene_id, asset_id=np.array(kept_ids), category=np.array([placements[k].category for k in keep]),
        translation=T.astype(np.float32), rotation=R.astype(np.float32), spatial=spatial, physical=rel.codes,
        room=room, extras={"room_type": np.asarray(room_type.name)},
    )
    return RoomResult(scene, room_type.name, len(placements), report, 0)
