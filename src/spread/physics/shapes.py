"""Collision shapes and mass frames of assets, built once per asset per pybullet client.

A body's collision shape is the compound of the asset's convex parts, each one an exact convex hull
(so concave assets keep their gaps). Two details make that exact in Bullet:

* **Margin.** Bullet rounds every hull outward by :data:`~spread.physics.params.BULLET_HULL_MARGIN`
  (1 mm), which would make objects float 1 mm per contact. Each part is therefore inset by the margin
  first (its face planes moved inward): inset hull ⊕ margin ball = the part, with edges rounded by 1 mm.
  A part thinner than four margins is inset by half its inradius instead (its shape grows by < 1 mm).
* **Body frame.** The body (link) frame is the asset's *principal inertial frame*: origin at the true
  centre of mass of the asset's watertight mesh (``mesh.center_mass``), axes along its principal axes
  of inertia. The parts are expressed in that frame, and Bullet's inertial frame coincides with the
  link frame, so every pybullet pose (create, get, reset) is the pose of the centre of mass and there is
  no frame ambiguity. :mod:`spread.physics.frames` converts to and from the Scene's bbox-centre poses.

Shapes are written as one Wavefront .obj with one ``o`` group per part; pybullet turns each group into a
convex hull child of one compound (``createCollisionShape(GEOM_MESH, fileName=...)``) — pybullet's
``createCollisionShapeArray`` accepts mesh files but not vertex lists, and files keep one code path.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from spread.physics.params import BULLET_HULL_MARGIN


@dataclass(frozen=True)
class BodyShape:
    """One asset's physics data on one client.

    collision_id: pybullet collision shape id (on the client that created it).
    com: (3,) centre of mass in the asset's canonical frame, metres.
    axes: (3, 3) principal axes of inertia as columns, in the canonical frame (a rotation, det +1).
        The body frame is ``v_canonical = com + axes @ v_body``.
    inertia_per_kg: (3,) principal moments of inertia divided by mass, m² (multiply by the mass).
    """

    collision_id: int
    com: np.ndarray
    axes: np.ndarray
    inertia_per_kg: np.ndarray


def mass_frame(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(com (3,), principal axes (3, 3) columns, inertia per kg (3,)) of a watertight trimesh, uniform density."""
    com = np.asarray(mesh.center_mass, np.float64)
    inertia = np.asarray(mesh.moment_inertia, np.float64) / float(mesh.mass)  # about com, per kg
    moments, axes = np.linalg.eigh(0.5 * (inertia + inertia.T))
    if np.linalg.det(axes) < 0:
        axes[:, -1] *= -1.0
    return com, axes, np.maximum(moments, 1e-12)


def parts_mass_frame(parts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`mass_frame` of a union of convex parts (trimesh each), uniform density, overlaps counted twice."""
    volumes = np.array([abs(float(p.volume)) for p in parts])
    total = float(volumes.sum())
    if not total > 0:
        raise ValueError("the convex parts enclose no volume")
    centres = np.array([np.asarray(p.center_mass, np.float64) for p in parts])
    com = (volumes[:, None] * centres).sum(0) / total
    inertia = np.zeros((3, 3))
    for part, v, c in zip(parts, volumes, centres):
        tensor = np.asarray(part.moment_inertia, np.float64) * (v / abs(float(part.mass)))  # about c, mass v
        d = c - com
        inertia += tensor + v * (float(d @ d) * np.eye(3) - np.outer(d, d))  # parallel axes
    moments, axes = np.linalg.eigh(0.5 * (inertia + inertia.T) / total)
    if np.linalg.det(axes) < 0:
        axes[:, -1] *= -1.0
    return com, axes, np.maximum(moments, 1e-12)


def asset_mass_frame(library, asset_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mass frame of an asset: its watertight mesh's (:func:`mass_frame`), or, for a mesh that bounds
    no volume of its own (open shells of imported assets), that of its convex parts — the shapes the
    physics world simulates."""
    mesh = library.mesh(asset_id)
    if mesh.is_watertight and float(mesh.volume) > 0:
        return mass_frame(mesh)
    return parts_mass_frame(library.convex_parts(asset_id))


def inset_convex(vertices: np.ndarray, margin: float) -> np.ndarray:
    """Vertices of the convex hull of ``vertices`` with every face plane moved inward by ``margin`` (metres).

    The inset is capped at half the hull's inradius (a thin board keeps a core); returns the input's hull
    vertices unchanged when the hull is degenerate.
    """
    from scipy.optimize import linprog
    from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

    pts = np.asarray(vertices, np.float64)
    try:
        hull = ConvexHull(pts)
    except QhullError:
        return pts
    normals, offsets = hull.equations[:, :3], hull.equations[:, 3]  # inside: n·x + offset ≤ 0, |n| = 1
    # Chebyshev centre: the deepest interior point and its distance to the boundary (the inradius).
    res = linprog(c=[0, 0, 0, -1], A_ub=np.hstack([normals, np.ones((len(normals), 1))]), b_ub=-offsets,
                  bounds=[(None, None)] * 3 + [(0, None)], method="highs")
    if not res.success or res.x[3] <= 0:
        return pts[hull.vertices]
    centre, inradius = res.x[:3], res.x[3]
    inset = min(margin, 0.5 * inradius)
    try:
        inner = HalfspaceIntersection(np.hstack([normals, (offsets + inset)[:, None]]), centre).intersections
    except QhullError:
        return pts[hull.vertices]
    return np.unique(np.round(inner, 12), axis=0)


def write_parts_obj(path: str | os.PathLike, parts_vertices: Sequence[np.ndarray]) -> None:
    """Write convex point sets as one .obj, one ``o`` group (hull faces from scipy) per part."""
    from scipy.spatial import ConvexHull

    lines, base = [], 1
    for k, pts in enumerate(parts_vertices):
        pts = np.asarray(pts, np.float64)
        faces = ConvexHull(pts).simplices
        lines.append(f"o part{k}")
        lines.extend("v %.17g %.17g %.17g" % tuple(v) for v in pts)
        lines.extend("f %d %d %d" % tuple(f + base) for f in faces)
        base += len(pts)
    with open(path, "w") as fh:
        fh.write("\n".join(lines) + "\n")


def body_parts(parts: Sequence, com: np.ndarray, axes: np.ndarray, margin: float = BULLET_HULL_MARGIN) -> list[np.ndarray]:
    """The asset's convex parts (trimesh, canonical frame) as inset point sets in the body frame."""
    out = []
    for part in parts:
        body = (np.asarray(part.vertices, np.float64) - com) @ axes  # v_body = axesᵀ (v − com)
        out.append(inset_convex(body, margin))
    return out
