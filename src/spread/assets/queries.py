"""What placement asks of asset records: size in a rest pose, and whether it fits on a surface.

Everything works from :class:`~spread.assets.library.AssetRecord` alone (no mesh loading). Sizes are
in metres; a rest pose's footprint is the xz size of the asset's bbox after the pose's rotation
(exact for the axis-aligned rest poses the catalog uses, a safe upper bound otherwise).
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from spread.assets.library import AssetLibrary, AssetRecord, RestPose, SupportSurface

#: How far (m, per side) an object may overhang an "inside" surface: the flat floor of a bowl or
#: basket is smaller than the opening, and what is dropped in comes to rest against the walls.
INSIDE_OVERHANG = 0.02


def posed_extents(record: AssetRecord, pose: RestPose | None = None) -> np.ndarray:
    """(3,) size of the asset's bbox after ``pose`` (default: its first, most common rest pose)."""
    pose = pose or record.rest_poses[0]
    return np.abs(np.asarray(pose.rotation)) @ np.asarray(record.extents)


def fits_on(record: AssetRecord, surface: SupportSurface, pose: RestPose | None = None,
            gap: float = 0.0, allow_quarter_turn: bool = True, overhang: float | None = None) -> bool:
    """Whether the asset in ``pose`` fits in the surface rectangle (``gap`` free on each side) and
    under its clearance. With ``allow_quarter_turn`` a 90° yaw may be used to make it fit.

    ``overhang`` (m per side) lets the footprint exceed the rectangle; by default 0, and
    :data:`INSIDE_OVERHANG` for "inside" surfaces (containers).
    """
    size = posed_extents(record, pose)
    if overhang is None:
        overhang = INSIDE_OVERHANG if surface.kind == "inside" else 0.0
    room_x = surface.xz_max[0] - surface.xz_min[0] - 2 * gap + 2 * overhang
    room_z = surface.xz_max[1] - surface.xz_min[1] - 2 * gap + 2 * overhang
    if size[1] > surface.clearance:
        return False
    if size[0] <= room_x and size[2] <= room_z:
        return True
    return allow_quarter_turn and size[2] <= room_x and size[0] <= room_z


def surfaces_of(record: AssetRecord, kinds: Iterable[str] | None = None) -> list[tuple[int, SupportSurface]]:
    """(index, surface) pairs of the record's support surfaces, optionally only the given kinds."""
    wanted = None if kinds is None else set(kinds)
    return [(k, s) for k, s in enumerate(record.support_surfaces) if wanted is None or s.kind in wanted]


def assets_fitting(library: AssetLibrary, surface: SupportSurface, categories: Iterable[str] | None = None,
                   role: str = "object", gap: float = 0.0) -> list[str]:
    """Ids of ``role`` assets (of ``categories``, default any) that fit on ``surface`` in some rest pose."""
    cats = None if categories is None else set(categories)
    out = []
    for aid in library:
        rec = library[aid]
        if rec.role != role or (cats is not None and rec.category not in cats):
            continue
        if any(fits_on(rec, surface, pose, gap) for pose in rec.rest_poses):
            out.append(aid)
    return out
