"""Turn a list of convex parts into an asset on disk: union mesh, canonical frame, record.

Assets are built from convex parts on purpose: the parts are then the *exact* physics collision
shapes (a shelf keeps its gaps; a convex hull or a coarse decomposition would fill them), and the
visual mesh is their watertight boolean union (manifold3d through trimesh). Both are shifted together
into the canonical frame (bbox centre at the origin), so mesh and parts agree exactly.

Candidate rest poses are checked for static stability (:mod:`spread.assets.stability`) and the
unstable ones dropped; an asset with none left is an error. Files are written only when their bytes
change, so rebuilding an unchanged library keeps every file (and its mtime and cache) as it was.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from spread.assets.library import AssetLibrary, AssetRecord, RestPose, SupportSurface, parts_bytes
from spread.assets.stability import stable_rest_poses
from spread.io import read_bytes_checked, write_bytes_atomic

#: Most faces allowed on an asset's visual mesh.
MAX_FACES = 5000


@dataclass
class AssetSpec:
    """What a category generator returns, in any frame with y up and the floor/base at its bottom.

    ``rest_poses`` are candidate rotations (name → 3×3) applied to the canonical mesh; the builder
    computes each one's ``bottom_offset``. ``support_surfaces`` are given in the same frame as the parts
    and are shifted with them into the canonical frame.
    """

    asset_id: str
    category: str
    variant: int
    role: str
    parts: list  # trimesh.Trimesh, each convex
    density: float
    rest_poses: dict[str, np.ndarray] = field(default_factory=lambda: {"upright": np.eye(3)})
    rest_weights: dict[str, float] = field(default_factory=dict)
    support_surfaces: list[SupportSurface] = field(default_factory=list)
    tags: list[str] = field(default_factory=list)


def union_mesh(parts: Sequence) -> "object":
    """Watertight boolean union of the parts (manifold3d). Raises if the result is not watertight.

    Vertices are merged when that keeps the mesh watertight; manifold's own output (watertight by
    construction, but with some coincident vertices) is kept otherwise.
    """
    import trimesh

    if len(parts) == 1:
        raw = parts[0].copy()
    else:
        raw = trimesh.boolean.union(list(parts), engine="manifold")
    mesh = trimesh.Trimesh(raw.vertices, raw.faces, process=True)
    if not mesh.is_watertight:
        mesh = trimesh.Trimesh(raw.vertices, raw.faces, process=False)
        mesh.remove_unreferenced_vertices()
    if not mesh.is_watertight:
        raise ValueError("union of the convex parts is not watertight")
    return mesh


def _write_if_changed(path: Path, data: bytes) -> None:
    """Write ``data`` atomically unless ``path`` already holds exactly these bytes."""
    if path.is_file() and path.stat().st_size == len(data) and read_bytes_checked(path, max_bytes=0) == data:
        return
    write_bytes_atomic(path, data)


def write_asset(root: str | Path, spec: AssetSpec) -> AssetRecord:
    """Write mesh + parts of ``spec`` under the library ``root`` and return its record.

    The index is not touched; the caller collects records and saves the index once. Files that
    already hold the same bytes are left alone.
    """
    import trimesh

    root = Path(root)
    for k, p in enumerate(spec.parts):
        if not p.is_convex:
            raise ValueError(f"asset '{spec.asset_id}': part {k} is not convex")
    mesh = union_mesh(spec.parts)
    if len(mesh.faces) > MAX_FACES:
        raise ValueError(f"asset '{spec.asset_id}': {len(mesh.faces)} faces exceed the budget of {MAX_FACES}")
    lo, hi = mesh.bounds
    centre = 0.5 * (lo + hi)
    mesh.apply_translation(-centre)
    parts = [trimesh.Trimesh(p.vertices - centre, p.faces, process=False) for p in spec.parts]
    surfaces = [
        SupportSurface(
            height=s.height - centre[1],
            xz_min=(s.xz_min[0] - centre[0], s.xz_min[1] - centre[2]),
            xz_max=(s.xz_max[0] - centre[0], s.xz_max[1] - centre[2]),
            clearance=s.clearance, kind=s.kind,
        )
        for s in spec.support_surfaces
    ]
    stable = stable_rest_poses(mesh, {n: np.asarray(R, np.float64) for n, R in spec.rest_poses.items()})
    if not stable:
        raise ValueError(f"asset '{spec.asset_id}': none of the rest poses {sorted(spec.rest_poses)} is stable")
    rest = []
    for name, R in stable.items():
        bottom = -(mesh.vertices @ R.T)[:, 1].min()
        rest.append(RestPose(name=name, rotation=R, bottom_offset=float(bottom),
                             weight=float(spec.rest_weights.get(name, 1.0))))
    mesh_file = f"meshes/{spec.asset_id}.glb"
    parts_file = f"parts/{spec.asset_id}.npz"
    mesh_data = mesh.export(file_type="glb")
    parts_data = parts_bytes(parts)
    _write_if_changed(root / mesh_file, mesh_data)
    _write_if_changed(root / parts_file, parts_data)
    volume = float(mesh.volume)
    return AssetRecord(
        asset_id=spec.asset_id, category=spec.category, variant=spec.variant, role=spec.role,
        extents=np.asarray(hi - lo, np.float64), volume=volume, density=float(spec.density),
        mass=volume * float(spec.density), mesh_file=mesh_file, parts_file=parts_file,
        num_parts=len(parts), num_faces=int(len(mesh.faces)),
        content_hash=hashlib.sha256(mesh_data + parts_data).hexdigest(),  # = file_sha256(mesh, parts)
        rest_poses=rest, support_surfaces=surfaces, tags=list(spec.tags),
    )


def library_from_specs(root: str | Path, specs: Sequence[AssetSpec]) -> AssetLibrary:
    """Write every spec and the index; the simplest way to make a small library (tests, examples)."""
    root = Path(root)
    records = {s.asset_id: write_asset(root, s) for s in specs}
    lib = AssetLibrary(root, records)
    lib.save_index()
    return lib


def box_part(size, centre=(0.0, 0.0, 0.0)):
    """An axis-aligned box part (metres)."""
    import trimesh

    return trimesh.creation.box(extents=np.asarray(size, float)).apply_translation(np.asarray(centre, float))


def box_asset(asset_id: str, size, category: str = "box", role: str = "object", density: float = 500.0,
              support_top: bool = True) -> AssetSpec:
    """A single-box asset, with its top face as a support surface: the unit of known-answer tests."""
    size = np.asarray(size, float)
    surfaces = []
    if support_top:
        surfaces.append(SupportSurface(height=size[1], xz_min=(-size[0] / 2, -size[2] / 2),
                                       xz_max=(size[0] / 2, size[2] / 2)))
    return AssetSpec(
        asset_id=asset_id, category=category, variant=0, role=role,
        parts=[box_part(size, (0, size[1] / 2, 0))], density=density, support_surfaces=surfaces,
    )
