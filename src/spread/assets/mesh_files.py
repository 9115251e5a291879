"""Real mesh files (glb, gltf, obj, ply) → one clean triangle mesh, as public asset sets ship them.

:func:`load_mesh_file` reads a file and returns a :class:`LoadedMesh`:

* **every body** of the file (glTF nodes, OBJ groups, ...) is posed by its scene-graph transform and
  merged into one mesh; point clouds and curves in the file are ignored;
* **units are kept**: no rescaling or recentring (glTF is metres by its specification; OBJ and PLY
  carry no unit and are taken as metres);
* **texture seams and duplicate vertices**: vertices at the same position (to 1e-8 m) are merged,
  whatever their texture coordinates or normals, so a cube split at its UV seams becomes one closed
  surface; zero-area and duplicate triangles and unused vertices are dropped;
* **winding** is made consistent within each connected piece, and each piece is oriented so that it
  encloses positive volume (its normals point outward); a flat piece keeps its orientation;
* **several closed bodies** (a chair whose legs are separate closed boxes pushed into the seat) are
  replaced by their exact boolean union (manifold3d) when every body is closed, so that the result is
  one closed surface without faces buried inside another body. When some body is open, the bodies are
  only concatenated; the metrics then tell inside from outside with the generalised winding number and
  ignore buried faces (:mod:`spread.metrics.solid`).

Errors (:class:`MeshFileError`) name the file: unreadable, unknown format, no triangles, non-finite
coordinates, zero area.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: File suffixes read by :func:`load_mesh_file`.
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply")
#: Vertices closer than this (metres, per coordinate rounding) are one vertex.
MERGE_DIGITS = 8
#: A mesh with less total area than this (m²) has no surface.
MIN_TOTAL_AREA = 1e-10


class MeshFileError(ValueError):
    """A mesh file cannot be used; the message names the file and the problem."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path, self.problem = str(path), problem
        super().__init__(f"{path}: {problem}")


@dataclass
class LoadedMesh:
    """A cleaned mesh in the file's own frame and units, and what was done to it.

    mesh: trimesh.Trimesh (process=False), float64 vertices.
    bodies: connected pieces in the file after merging seams; unioned: they were replaced by their
    boolean union; watertight: the final mesh is closed (every edge shared by exactly two faces).
    merged_vertices: vertices removed by merging seams and duplicates.
    """

    mesh: object
    bodies: int
    unioned: bool
    watertight: bool
    merged_vertices: int
    dropped_faces: int

    def info(self) -> dict:
        return {"bodies": self.bodies, "unioned": self.unioned, "watertight": self.watertight,
                "merged_vertices": self.merged_vertices, "dropped_faces": self.dropped_faces,
                "faces": int(len(self.mesh.faces)), "vertices": int(len(self.mesh.vertices))}


def _read_triangles(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """All triangle geometry of the file, posed by the scene graph, concatenated: (V, 3), (F, 3)."""
    import trimesh

    from spread.io import InputFileError, check_input_file

    try:
        check_input_file(path)  # a FIFO or device is refused by name, never opened
    except InputFileError as exc:
        raise MeshFileError(path, str(exc).removeprefix(f"{path}: ")) from None
    try:
        loaded = trimesh.load(str(path), force="scene", process=False)  # checked: check_input_file above
    except Exception as exc:  # trimesh raises many types for broken files
        raise MeshFileError(path, f"unreadable mesh file ({type(exc).__name__}: {exc})") from exc
    try:
        geometries = loaded.dump(concatenate=False)
    except Exception as exc:
        raise MeshFileError(path, f"cannot resolve the file's scene graph ({type(exc).__name__}: {exc})") from exc
    vertices, faces, offset = [], [], 0
    for geom in geometries:
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        v = np.asarray(geom.vertices, np.float64)
        f = np.asarray(geom.faces, np.int64)
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    if not faces:
        raise MeshFileError(path, "no triangles in the file (empty, or points/lines only)")
    return np.concatenate(vertices), np.concatenate(faces)


def _orient_pieces(mesh) -> None:
    """Consistent winding per connected piece, and each piece enclosing positive signed volume."""
    import trimesh

    trimesh.repair.fix_winding(mesh)
    labels = trimesh.graph.connected_component_labels(mesh.face_adjacency, node_count=len(mesh.faces))
    tri = mesh.triangles
    faces = np.asarray(mesh.faces).copy()
    for label in np.unique(labels):
        sel = labels == label
        t = tri[sel]
        centre = t.reshape(-1, 3).mean(0)
        a, b, c = t[:, 0] - centre, t[:, 1] - centre, t[:, 2] - centre
        volume = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
        scale = np.ptp(t.reshape(-1, 3), axis=0).max() ** 3
        if volume < -1e-9 * max(scale, 1e-30):
            faces[sel] = faces[sel][:, ::-1]
    mesh.faces = faces


def _union_if_closed(mesh):
    """(mesh, unioned, bodies): the boolean union of the bodies when there are several and all are closed."""
    import trimesh

    bodies = mesh.split(only_watertight=False, repair=False)  # repair would fill small holes
    if len(bodies) < 2 or not all(b.is_watertight for b in bodies):
        return mesh, False, len(bodies)
    try:
        union = trimesh.boolean.union(list(bodies), engine="manifold")
    except Exception:
        return mesh, False, len(bodies)
    union = trimesh.Trimesh(np.asarray(union.vertices, np.float64), np.asarray(union.faces, np.int64), process=True)
    if not union.is_watertight or union.volume <= 0:
        return mesh, False, len(bodies)
    return union, True, len(bodies)


def clean_mesh(vertices: np.ndarray, faces: np.ndarray, source: str = "<arrays>") -> LoadedMesh:
    """Merge seams, drop degenerate/duplicate faces, orient pieces, union closed bodies (module docstring)."""
    import trimesh

    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    if not np.isfinite(vertices).all():
        raise MeshFileError(source, "non-finite vertex coordinates (NaN or inf)")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise MeshFileError(source, "no triangles")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshFileError(source, "a face indexes a vertex that does not exist")
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    n_vertices, n_faces = len(mesh.vertices), len(mesh.faces)
    mesh.merge_vertices(merge_tex=True, merge_norm=True, digits_vertex=MERGE_DIGITS)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0 or float(mesh.area) < MIN_TOTAL_AREA:
        raise MeshFileError(source, f"zero surface area ({n_faces} faces, all degenerate)")
    _orient_pieces(mesh)
    mesh, unioned, bodies = _union_if_closed(mesh)
    out = trimesh.Trimesh(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), process=False)
    return LoadedMesh(out, bodies, unioned, bool(out.is_watertight), n_vertices - len(out.vertices) if not unioned
                      else 0, n_faces - len(out.faces) if not unioned else 0)


def load_mesh_file(path: str | os.PathLike) -> LoadedMesh:
    """Read and clean one mesh file (module docstring); raises :class:`MeshFileError` naming the file."""
    path = Path(path)
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise MeshFileError(path, f"unknown mesh format '{path.suffix}' (expected one of {', '.join(MESH_SUFFIXES)})")
    if not path.is_file():
        raise MeshFileError(path, "mesh file does not exist")
    vertices, faces = _read_triangles(path)
    return clean_mesh(vertices, faces, source=str(path))
