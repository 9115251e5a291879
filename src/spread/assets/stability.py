"""Static stability of a rest pose: does a mesh, rotated and set on a flat floor, stay put?

A pose is stable when the centre of mass, projected onto the floor (xz), lies inside the support
polygon — the convex hull of the vertices within :data:`CONTACT_TOLERANCE` of the lowest point —
with a margin of at least ``min(MIN_MARGIN, INRADIUS_FRACTION × inradius)``: 3 mm for ordinary
contact patches, 10 % of the patch's inradius for very narrow ones (a pencil on a face of its
hexagon). And it must not roll: across every edge of the support polygon, the polygon must be at
least :data:`MIN_SUPPORT_RATIO` as wide as the object itself. A round cylinder on its side has a
line of contact, no polygon; an n-sided prism on a face has the ratio sin(π/n), so 16 or more sides
(≤ 0.195) roll like the cylinder they approximate, while an 8–12 sided prism (0.38–0.26) rests.

Frames: ``rotation`` is world-from-local for the canonical mesh (metres, y-up); the floor is
horizontal, so only the rotated y matters for the contact and x, z for the polygon.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Vertices within this height (metres) of the lowest one touch the floor.
CONTACT_TOLERANCE = 1e-3
#: Required distance (metres) from the projected centre of mass to the support polygon's edge...
MIN_MARGIN = 3e-3
#: ...or this fraction of the polygon's inradius, whichever is smaller.
INRADIUS_FRACTION = 0.1
#: Smallest ratio of the support polygon's width to the object's width, across any polygon edge.
MIN_SUPPORT_RATIO = 0.2


@dataclass
class StabilityCheck:
    """Outcome for one pose: ``margin`` (m, negative outside) against ``required`` (m), and the
    narrowest support-to-object width ratio ``support_ratio`` against :data:`MIN_SUPPORT_RATIO`."""

    stable: bool
    margin: float
    required: float
    support_ratio: float
    support_xz: np.ndarray  # (K, 2) CCW support polygon, empty when there is none


def _inward_normals(polygon: np.ndarray) -> np.ndarray:
    """Unit inward normals (K, 2) of the edges ``polygon[k] → polygon[k+1]`` of a CCW polygon."""
    edge = np.roll(polygon, -1, axis=0) - polygon
    return np.stack([-edge[:, 1], edge[:, 0]], 1) / np.linalg.norm(edge, axis=1, keepdims=True)


def _edge_distances(polygon: np.ndarray, point: np.ndarray) -> np.ndarray:
    """Signed distances of ``point`` to each edge line of a CCW convex polygon (positive inside)."""
    return np.einsum("ij,ij->i", point - polygon, _inward_normals(polygon))


def _support_ratio(polygon: np.ndarray, body_xz: np.ndarray) -> float:
    """Min over the polygon's edges of (polygon width / body width) along the edge's inward normal."""
    inward = _inward_normals(polygon)
    poly_width = np.einsum("kij,kj->ki", polygon[None] - polygon[:, None], inward).max(axis=1)
    body_proj = body_xz @ inward.T
    return float((poly_width / np.ptp(body_proj, axis=0)).min())


def support_polygon(vertices: np.ndarray, tolerance: float = CONTACT_TOLERANCE) -> np.ndarray:
    """CCW convex hull (K, 2) in xz of the vertices touching the floor; empty (0, 2) for a line/point."""
    from scipy.spatial import ConvexHull, QhullError

    low = vertices[:, 1].min()
    contact = np.unique(vertices[vertices[:, 1] <= low + tolerance][:, [0, 2]].round(9), axis=0)
    if len(contact) < 3:
        return np.zeros((0, 2))
    try:
        hull = ConvexHull(contact)
    except QhullError:  # collinear contact: a line, not an area
        return np.zeros((0, 2))
    if hull.volume < 1e-10:  # 2D "volume" is the area
        return np.zeros((0, 2))
    return contact[hull.vertices]


def check_rest_pose(mesh, rotation: np.ndarray) -> StabilityCheck:
    """Stability of the canonical ``mesh`` (trimesh, watertight) turned by ``rotation`` onto a floor."""
    R = np.asarray(rotation, np.float64)
    vertices = np.asarray(mesh.vertices) @ R.T
    com_xz = (R @ np.asarray(mesh.center_mass))[[0, 2]]
    polygon = support_polygon(vertices)
    if len(polygon) == 0:
        return StabilityCheck(False, -np.inf, MIN_MARGIN, 0.0, polygon)
    margin = float(_edge_distances(polygon, com_xz).min())
    inradius = float(max(_edge_distances(polygon, polygon.mean(0)).min(), 0.0))  # lower bound
    required = min(MIN_MARGIN, INRADIUS_FRACTION * inradius)
    ratio = _support_ratio(polygon, vertices[:, [0, 2]])
    return StabilityCheck(margin >= required and ratio >= MIN_SUPPORT_RATIO, margin, required, ratio, polygon)


def stable_rest_poses(mesh, candidates: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The candidates (name → rotation) that pass :func:`check_rest_pose`, in their given order."""
    return {name: R for name, R in candidates.items() if check_rest_pose(mesh, R).stable}
