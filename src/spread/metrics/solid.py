"""Inside/outside and signed distances for meshes as shipped: open, non-manifold, self-intersecting.

A watertight mesh bounds a volume and trimesh's ray test says which points are in it. A real mesh may not
bound anything: an open-topped cup made of one layer of triangles, a table whose unseen bottom faces were
deleted, a chair whose legs are separate closed boxes pushed into the seat. Here the **solid** of a mesh
is where its *generalised winding number* exceeds one half (Jacobson, Kavan, Sorkine-Hornung 2013):

    w(p) = (1 / 4π) Σ_f Ω_f(p),   inside ⇔ w(p) > 1/2,

with Ω_f the signed solid angle of triangle f seen from p (libigl's fast winding number: exact near
field, Barnes–Hut far field). For a closed, outward-oriented surface w is 1 inside and 0 outside, so
this is the ordinary solid. For an open cup w is ≈ 1 in its cavity well below the rim, ½ across the
opening, < ½ above it: the cup counts as filled up to its opening (a single layer of triangles bounds no
wall thickness; :mod:`spread.assets.mesh_files` orients each piece outward first). Overlapping closed
bodies give w = 2 where they overlap: inside, as it should be.

**The distance** of a point is its distance to the *bounding faces* of the mesh: every non-degenerate
face except those buried in the solid — faces with w > :data:`BURIED_WINDING` on both sides (the part
of a chair leg pushed into the seat). The **signed distance** is minus that distance inside the solid
and plus it outside: positive outside, as everywhere in :mod:`spread.metrics`.

What an open mesh does to the numbers (docs/evaluation.md): a point that sits in the opening of a
single-layer container is inside by the winding number and its depth is its distance to the walls, so
an object reaching into a single-layer cup from above counts as penetrating it by that much; where a
flat, single-layer piece (a sheet) lies, every point is outside and its distance is the distance to the
sheet. A mesh whose faces are all degenerate has no surface and no answer (an error naming the asset).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Inside when the winding number exceeds this.
INSIDE_WINDING = 0.5
#: A face with a winding number above this on both sides is buried in the solid (not a boundary).
BURIED_WINDING = 0.75
#: Offset of the two probes of a face (relative to the mesh's bounding-box diagonal).
PROBE_OFFSET = 1e-6


@dataclass(frozen=True)
class SolidMesh:
    """A mesh prepared for winding numbers and distances to its bounding faces (canonical frame, metres).

    vertices (V, 3) float64; faces (F, 3) int64 non-degenerate faces (winding numbers use them all);
    bounding (B,) int64 indices of the faces that bound the solid (distances use them); lo, hi its AABB.
    """

    vertices: np.ndarray
    faces: np.ndarray
    bounding: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    tree: object  # igl.AABB over vertices, faces[bounding]

    @property
    def buried(self) -> int:
        return int(len(self.faces) - len(self.bounding))

    def winding_number(self, points: np.ndarray) -> np.ndarray:
        """(P,) generalised winding numbers of points (P, 3)."""
        import igl

        pts = np.ascontiguousarray(points, np.float64)
        if len(pts) == 0:
            return np.zeros(0)
        return np.asarray(igl.fast_winding_number(self.vertices, self.faces, pts), np.float64)

    def inside(self, points: np.ndarray) -> np.ndarray:
        """(P,) bool: in the solid (winding number > 1/2, and within the AABB: outside the mesh's convex
        hull the winding number is at most 1/2 anyway, so this only removes round-off)."""
        pts = np.asarray(points, np.float64)
        in_box = np.all((pts >= self.lo) & (pts <= self.hi), axis=1)
        out = np.zeros(len(pts), bool)
        if in_box.any():
            out[in_box] = self.winding_number(pts[in_box]) > INSIDE_WINDING
        return out

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(P,) distance (metres) of points (P, 3) to the bounding faces."""
        pts = np.ascontiguousarray(points, np.float64)
        if len(pts) == 0:
            return np.zeros(0)
        sq, _, _ = self.tree.squared_distance(self.vertices, self.faces[self.bounding], pts)
        return np.sqrt(np.maximum(np.asarray(sq, np.float64), 0.0))

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """(P,) signed distance, **positive outside**, metres (module docstring)."""
        d = self.distance(points)
        return np.where(self.inside(points), -d, d)


def solid_mesh(mesh, name: str = "mesh") -> SolidMesh:
    """The :class:`SolidMesh` of a trimesh (module docstring); ``ValueError`` naming ``name`` when the mesh
    has no non-degenerate face."""
    import igl

    vertices = np.ascontiguousarray(mesh.vertices, np.float64)
    faces = np.asarray(mesh.faces, np.int64)
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    keep = area2 > 1e-20
    if not keep.any():
        raise ValueError(f"{name}: every face is degenerate; the mesh has no surface to measure against")
    faces = np.ascontiguousarray(faces[keep])
    normals = cross[keep] / area2[keep, None]
    centres = tri[keep].mean(1)
    lo, hi = vertices.min(0), vertices.max(0)
    eps = PROBE_OFFSET * max(float(np.linalg.norm(hi - lo)), 1e-9)
    probes = np.concatenate([centres + eps * normals, centres - eps * normals])
    w = np.asarray(igl.fast_winding_number(vertices, faces, probes), np.float64)
    w_out, w_in = w[:len(faces)], w[len(faces):]
    bounding = np.flatnonzero(~((w_out > BURIED_WINDING) & (w_in > BURIED_WINDING))).astype(np.int64)
    if len(bounding) == 0:
        raise ValueError(f"{name}: no face bounds the solid (every face is buried)")
    tree = igl.AABB()
    tree.init(vertices, np.ascontiguousarray(faces[bounding]))
    return SolidMesh(vertices, faces, bounding, lo, hi, tree)
