"""Small objects on support surfaces: table tops, every shelf level, counters, beds, sofas; stacks of
the same asset (books, plates, bowls); objects on objects (fruit in a bowl, a phone on a book).

Each object gets a sampled rest pose, a uniform random yaw, and a spot whose posed xz footprint lies
inside the parent surface's rectangle (inset) without touching the footprints already on that surface;
its height must fit the surface's clearance (the gap to the shelf board above). Objects start
``drop_height`` above their surface; physics settles them afterwards.
"""

from __future__ import annotations

import math

import numpy as np

from spread.assets.queries import INSIDE_OVERHANG
from spread.procgen.placement import Placement, footprint, surface_polygon, yaw_matrix
from spread.procgen.room_types import CONTAINER_CONTENTS, FURNITURE_AFFINITY, STACKABLE, RoomConfig

#: Keep footprints this far (metres) inside a surface's edge.
SURFACE_INSET = 0.02
#: An object must be this much lower (metres) than its surface's clearance.
CLEARANCE_MARGIN = 0.015


class _Surface:
    """A support rectangle of a placed parent, in world coordinates, with what already stands on it."""

    def __init__(self, parent: int, index: int, placement: Placement, surface, inset: float):
        self.parent, self.index = parent, index
        self.height = float(placement.translation[1] + placement.rotation[1] @ np.array([0.0, surface.height, 0.0]))
        self.polygon = surface_polygon(surface.xz_min, surface.xz_max, placement.rotation, placement.translation,
                                       inset)
        self.clearance = surface.clearance
        self.occupied: list = []

    @property
    def area(self) -> float:
        return float(self.polygon.area) if not self.polygon.is_empty else 0.0


def _sample_rest(record, rng: np.random.Generator):
    weights = np.array([p.weight for p in record.rest_poses], float)
    return record.rest_poses[int(rng.choice(len(weights), p=weights / weights.sum()))]


def _try_place(asset_id: str, record, surface: _Surface, hull: np.ndarray, rng: np.random.Generator,
               config: RoomConfig, tries: int = 12, parent_index: int | None = None) -> Placement | None:
    rest = _sample_rest(record, rng)
    height = float(np.abs(rest.rotation[1]) @ record.extents)
    if height > surface.clearance - CLEARANCE_MARGIN:
        return None
    if surface.polygon.is_empty:
        return None
    x0, z0, x1, z1 = surface.polygon.bounds
    for _ in range(tries):
        R = yaw_matrix(rng.uniform(0, 2 * math.pi)) @ rest.rotation
        t = np.array([rng.uniform(x0, x1), surface.height + rest.bottom_offset + config.drop_height,
                      rng.uniform(z0, z1)])
        fp = footprint(hull, R, t)
        if not surface.polygon.contains(fp):
            continue
        if any(fp.distance(other) < config.object_gap for other in surface.occupied):
            continue
        surface.occupied.append(fp)
        return Placement(asset_id, record.category, record.role, R, t, parent=surface.parent,
                         surface=surface.index, rest=rest.name, extents=np.asarray(record.extents, float))
    return None


def populate(placements: list[Placement], library, rng: np.random.Generator, config: RoomConfig,
             hulls: dict[str, np.ndarray], max_objects: int) -> list[Placement]:
    """Add small objects to ``placements`` (furniture already on the floor) up to ``max_objects`` in all."""
    surfaces: list[_Surface] = []
    for idx, p in enumerate(placements):
        rec = library[p.asset_id]
        for k, s in enumerate(rec.support_surfaces):
            surf = _Surface(idx, k, p, s, SURFACE_INSET)
            if surf.area > 0.004:
                surfaces.append(surf)
    total_area = sum(s.area for s in surfaces)
    if not surfaces:
        return placements
    budget = max_objects - len(placements)
    target = min(budget, max(int(rng.poisson(config.object_density * total_area)), config.min_objects))
    attempts = 0
    while target > 0 and attempts < 8 * target + 20:
        attempts += 1
        placed_now = len(placements)
        if placed_now - _n_furniture(placements) >= target or placed_now >= max_objects:
            break
        surf = surfaces[int(rng.choice(len(surfaces), p=np.array([s.area for s in surfaces]) / total_area))]
        parent = placements[surf.parent]
        choices = [c for c in FURNITURE_AFFINITY.get(parent.category, ()) if library.ids_of(c)]
        if not choices:
            continue
        category = choices[int(rng.integers(len(choices)))]
        ids = library.ids_of(category)
        asset_id = ids[int(rng.integers(len(ids)))]
        obj = _try_place(asset_id, library[asset_id], surf, hulls[asset_id], rng, config)
        if obj is None:
            continue
        placements.append(obj)
        base = len(placements) - 1
        if category in STACKABLE and rng.random() < config.stack_probability:
            _stack(placements, base, library, rng, config, surf.clearance, max_objects)
        elif category in CONTAINER_CONTENTS and rng.random() < config.on_object_probability:
            _fill(placements, base, library, rng, config, hulls, max_objects)
    return placements


def _n_furniture(placements: list[Placement]) -> int:
    return sum(1 for p in placements if p.parent is None)


def _stack(placements: list[Placement], base: int, library, rng: np.random.Generator, config: RoomConfig,
           clearance: float, max_objects: int) -> None:
    """Copies of the base object on top of each other, aligned within a few millimetres."""
    rec = library[placements[base].asset_id]
    rest = next(p for p in rec.rest_poses if p.name == placements[base].rest)
    height = float(np.abs(rest.rotation[1]) @ rec.extents)
    n_more = int(rng.integers(1, max(2, config.max_stack)))
    below = base
    bottom = placements[base].translation[1] - rest.bottom_offset - config.drop_height
    for level in range(1, n_more + 1):
        if len(placements) >= max_objects or (level + 1) * height > clearance - CLEARANCE_MARGIN:
            break
        prev = placements[below]
        R = yaw_matrix(rng.uniform(-0.08, 0.08)) @ prev.rotation
        t = prev.translation + np.array([rng.uniform(-0.004, 0.004), 0.0, rng.uniform(-0.004, 0.004)])
        t[1] = bottom + level * (height + config.drop_height) + rest.bottom_offset
        placements.append(Placement(prev.asset_id, prev.category, prev.role, R, t, parent=below,
                                    rest=prev.rest, extents=prev.extents))
        below = len(placements) - 1


def _fill(placements: list[Placement], base: int, library, rng: np.random.Generator, config: RoomConfig,
          hulls: dict[str, np.ndarray], max_objects: int) -> None:
    """Objects on an object: fruit in a bowl, a phone on a book (only on an upright parent)."""
    parent = placements[base]
    rec = library[parent.asset_id]
    rest = next((p for p in rec.rest_poses if p.name == parent.rest), None)
    # support surfaces are given in the canonical frame: usable only when the rest pose keeps it
    if rest is None or not np.allclose(rest.rotation, np.eye(3)) or not rec.support_surfaces:
        return
    options = [c for c in CONTAINER_CONTENTS[parent.category] if library.ids_of(c)]
    if not options:
        return
    for k, s in enumerate(rec.support_surfaces):
        # inside a bowl or basket, contents may overhang the flat floor onto the sloping walls
        inset = -INSIDE_OVERHANG if getattr(s, "kind", "top") == "inside" else 0.003
        surf = _Surface(base, k, parent, s, inset)
        for _ in range(int(rng.integers(1, 4))):
            if len(placements) >= max_objects:
                return
            category = options[int(rng.integers(len(options)))]
            ids = library.ids_of(category)
            asset_id = ids[int(rng.integers(len(ids)))]
            obj = _try_place(asset_id, library[asset_id], surf, hulls[asset_id], rng, config, tries=8)
            if obj is not None:
                placements.append(obj)
