"""A placed object before physics: pose, intended supporter, and its footprint in the xz plane."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def yaw_matrix(angle: float) -> np.ndarray:
    """Rotation about world +y by ``angle`` radians (local +z turns towards +x for positive angles)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass
class Placement:
    """One object of a room being generated (metres, world frame, y-up).

    ``parent`` is the index of the object it was placed on (``None``: the floor); ``surface`` is the
    index of the parent's support surface it sits on; ``rest`` names the rest pose used.
    """

    asset_id: str
    category: str
    role: str
    rotation: np.ndarray
    translation: np.ndarray
    parent: int | None
    surface: int | None = None
    rest: str = "upright"
    extents: np.ndarray | None = None  # canonical bbox size of the asset

    def half_extent_along(self, direction: np.ndarray) -> float:
        """Half the posed bbox size along a world direction (metres)."""
        local = self.rotation.T @ np.asarray(direction, float)
        return 0.5 * float(np.abs(local) @ self.extents)


def footprint(hull_vertices: np.ndarray, rotation: np.ndarray, translation: np.ndarray):
    """World xz footprint (shapely Polygon) of a posed object from its canonical hull vertices."""
    from shapely import MultiPoint

    w = hull_vertices @ rotation.T + translation
    return MultiPoint(w[:, [0, 2]]).convex_hull


def surface_polygon(xz_min, xz_max, rotation: np.ndarray, translation: np.ndarray, inset: float = 0.0):
    """World xz polygon of a parent's support rectangle (local xz_min..xz_max), shrunk by ``inset``
    (metres; a negative inset grows it)."""
    from shapely import Polygon

    (x0, z0), (x1, z1) = xz_min, xz_max
    corners = np.array([[x0, 0, z0], [x1, 0, z0], [x1, 0, z1], [x0, 0, z1]], float)
    w = corners @ rotation.T + translation
    poly = Polygon(w[:, [0, 2]])
    return poly.buffer(-inset, join_style="mitre") if inset != 0 else poly
