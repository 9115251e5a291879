"""Imported assets: a real mesh file → an asset of the library (mesh, convex parts, record, caches).

Frames and units: the file's mesh, cleaned (:func:`spread.assets.mesh_files.load_mesh_file`: bodies
merged, seams welded, units kept), is shifted so that its bounding-box centre is the origin — the
library's canonical frame (DESIGN §3). ``scale_to`` (3,) optionally scales it per axis to those extents
(3D-FRONT objects are their 3D-FUTURE model scaled to the box of the scene file).

What an imported asset stores (``AssetRecord.source``): the file, its SHA-256, what cleaning did, the
canonical offset (the bbox centre in the file's frame, metres), whether the mesh is closed, and the
convex decomposition (method, settings, parts, seconds) with its fidelity (Hausdorff distance to the
mesh, :func:`spread.assets.decompose.decomposition_fidelity`).

Mass: volume × density, the volume being the mesh's when it is closed and the convex parts' total
otherwise (an open shell encloses no volume of its own; its parts are what the physics world simulates).

Caches, keyed by content:

* the decomposition of a canonical mesh, ``decompositions/<sha256 of mesh + method + settings>.npz``
  (+ ``.json`` with its fidelity): a mesh imported again, or the same 3D-FUTURE model at another scale,
  is not decomposed again (the parts of a scaled mesh are the scaled parts: an affine map keeps
  convexity);
* ``records/<asset_id>.json``: the record and a fingerprint of the inputs (file hash, category, scale,
  settings), so a re-run skips assets whose inputs and files are unchanged (resumable);
* the library's own geometry caches (surface samples, xz hull), built per content hash as for every asset.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from spread.assets.library import (
    AssetRecord, RestPose, load_parts, parts_bytes, reusable_record, write_record_sidecar,
)
from spread.checks import whole_number
from spread.io import file_sha256, read_bytes_checked, read_json, write_bytes_atomic, write_json_atomic

#: Bump when the files written for unchanged inputs change.
IMPORT_VERSION = 1
#: Density (kg/m³) of an imported asset whose category the procedural catalog does not know: an
#: effective density of furniture-like objects (solid wood ~600, hollow casings lighter).
DEFAULT_DENSITY = 400.0
#: An asset whose largest extent exceeds this (metres) is "furniture", else "object" (procgen roles).
FURNITURE_EXTENT = 0.6


@dataclass
class ImportSettings:
    """decomposition: "coacd", "vhacd" or "hull" (:mod:`spread.assets.decompose`); decomposition_settings: overrides of its settings;
    density: kg/m³ for unknown categories (known ones use the catalog's); fidelity_samples: samples per
    surface for the Hausdorff distance (0: not measured)."""

    decomposition: str = "coacd"
    decomposition_settings: dict = field(default_factory=dict)
    density: float = DEFAULT_DENSITY
    fidelity_samples: int = 2000

    def check(self) -> None:
        """``ValueError`` naming the setting an import could not build an asset with (before its first asset)."""
        import math

        from spread.assets.decompose import check_decomposition

        check_decomposition(str(self.decomposition), dict(self.decomposition_settings))
        if not (isinstance(self.density, (int, float)) and math.isfinite(self.density) and self.density > 0):
            raise ValueError(f"density={self.density!r}: a finite number of kg/m³ > 0")
        whole_number(self.fidelity_samples, "fidelity_samples", note="(0: not measured)")

    def fingerprint(self) -> dict:
        return {"decomposition": self.decomposition, "decomposition_settings": dict(self.decomposition_settings),
                "density": float(self.density), "fidelity_samples": int(self.fidelity_samples)}


def category_density(category: str, default: float) -> float:
    """The catalog's density of ``category`` when it has one, else ``default`` (kg/m³)."""
    from spread.assets.catalog import CATALOG

    info = CATALOG.get(category)
    return float(info.density) if info is not None else float(default)


def _mesh_key(mesh) -> str:
    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, np.int64).tobytes())
    return h.hexdigest()


def cached_decomposition(root: Path, mesh, settings: ImportSettings) -> tuple[list, dict]:
    """(parts, info) of the canonical ``mesh``: from ``root/decompositions`` when there, else computed,
    measured and stored (module docstring)."""
    import trimesh

    from spread.assets.decompose import convex_decomposition, decomposition_fidelity

    key = hashlib.sha256(json.dumps({"mesh": _mesh_key(mesh), "method": settings.decomposition,
                                     "settings": settings.decomposition_settings,
                                     "fidelity_samples": settings.fidelity_samples,
                                     "version": IMPORT_VERSION}, sort_keys=True).encode()).hexdigest()
    npz, meta = root / "decompositions" / f"{key[:32]}.npz", root / "decompositions" / f"{key[:32]}.json"
    if npz.exists() and meta.exists():
        try:
            return load_parts(npz), read_json(meta)
        except (OSError, ValueError, KeyError):
            pass  # torn cache: decompose again
    dec = convex_decomposition(mesh, method=settings.decomposition, **settings.decomposition_settings)
    info = dec.info()
    if settings.fidelity_samples > 0:
        info["fidelity"] = decomposition_fidelity(mesh, dec.parts, samples=settings.fidelity_samples)
    write_bytes_atomic(npz, parts_bytes(dec.parts))
    write_json_atomic(meta, info)
    return [trimesh.Trimesh(p.vertices, p.faces, process=False) for p in dec.parts], info


def parts_volume(parts) -> float:
    return float(sum(abs(p.volume) for p in parts))


def _write_if_changed(path: Path, data: bytes) -> None:
    if path.is_file() and path.stat().st_size == len(data) and read_bytes_checked(path, max_bytes=0) == data:
        return
    write_bytes_atomic(path, data)


def write_imported_asset(root: Path, asset_id: str, mesh, parts, category: str, density: float,
                         source: dict) -> AssetRecord:
    """Write a canonical mesh and its convex parts as asset ``asset_id`` (files only; returns the record)."""
    mesh_file, parts_file = f"meshes/{asset_id}.glb", f"parts/{asset_id}.npz"
    mesh_data = mesh.export(file_type="glb")
    part_data = parts_bytes(parts)
    _write_if_changed(root / mesh_file, mesh_data)
    _write_if_changed(root / parts_file, part_data)
    closed = bool(mesh.is_watertight)
    volume = float(mesh.volume) if closed and mesh.volume > 0 else parts_volume(parts)
    lo, hi = mesh.bounds
    extents = np.asarray(hi - lo, np.float64)
    bottom = float(-lo[1])
    return AssetRecord(
        asset_id=asset_id, category=category, variant=0,
        role="furniture" if extents.max() > FURNITURE_EXTENT else "object",
        extents=extents, volume=volume, density=float(density), mass=volume * float(density),
        mesh_file=mesh_file, parts_file=parts_file, num_parts=len(parts), num_faces=int(len(mesh.faces)),
        content_hash=hashlib.sha256(mesh_data + part_data).hexdigest(),
        rest_poses=[RestPose("upright", np.eye(3), bottom)], support_surfaces=[],
        tags=["imported"] + ([] if closed else ["open"]), source={**source, "closed": closed},
    )


def import_mesh_asset(root: str | Path, asset_id: str, mesh_path: str | Path, category: str,
                      settings: ImportSettings | None = None, scale_to=None) -> tuple[AssetRecord, bool]:
    """Import one mesh file as asset ``asset_id`` under library ``root``; returns (record, built).

    ``built`` is False when the asset was already there with the same inputs (nothing was done).
    Raises :class:`~spread.assets.mesh_files.MeshFileError` (unreadable, empty, zero area) naming the file.
    """
    import trimesh

    from spread.assets.mesh_files import load_mesh_file

    root, mesh_path = Path(root), Path(mesh_path)
    settings = settings or ImportSettings()
    file_hash = file_sha256(mesh_path) if mesh_path.is_file() else None
    target = None if scale_to is None else np.asarray(scale_to, np.float64).round(6)
    fingerprint = hashlib.sha256(json.dumps({
        "version": IMPORT_VERSION, "file_sha256": file_hash, "category": category,
        "scale_to": None if target is None else target.tolist(), "settings": settings.fingerprint(),
    }, sort_keys=True).encode()).hexdigest()
    rec = reusable_record(root, asset_id, fingerprint)
    if rec is not None:
        return rec, False
    loaded = load_mesh_file(mesh_path)
    mesh = loaded.mesh
    lo, hi = mesh.bounds
    centre = 0.5 * (lo + hi)
    canonical = trimesh.Trimesh(mesh.vertices - centre, mesh.faces, process=False)
    parts, decomposition = cached_decomposition(root, canonical, settings)
    scale = np.ones(3)
    if target is not None:
        extents = hi - lo
        if (target <= 0).any() or not np.isfinite(target).all():
            raise ValueError(f"{mesh_path}: target extents {target.tolist()} must be finite and > 0")
        scale = np.where(extents > 1e-9, target / np.maximum(extents, 1e-9), 1.0)
        canonical = trimesh.Trimesh(canonical.vertices * scale, canonical.faces, process=False)
        from spread.assets.decompose import convex_part

        parts = [convex_part(np.asarray(p.vertices) * scale) for p in parts]
    source = {"file": str(mesh_path), "sha256": file_hash, "cleaning": loaded.info(),
              "canonical_offset": [float(v) for v in centre], "scale": [float(v) for v in scale],
              "decomposition": decomposition}
    density = category_density(category, settings.density)
    rec = write_imported_asset(root, asset_id, canonical, parts, category, density, source)
    write_record_sidecar(root, asset_id, fingerprint, rec)
    return rec, True


def import_box_asset(root: str | Path, asset_id: str, extents, category: str,
                     settings: ImportSettings | None = None) -> tuple[AssetRecord, bool]:
    """An oriented box of ``extents`` (metres) as asset ``asset_id``: the stand-in for an object whose
    mesh is not available. Exact (its single part is itself). Returns (record, built)."""
    from spread.assets.assemble import box_asset, write_asset

    root = Path(root)
    settings = settings or ImportSettings()
    extents = np.asarray(extents, np.float64)
    if extents.shape != (3,) or not np.isfinite(extents).all() or (extents <= 0).any():
        raise ValueError(f"asset '{asset_id}': box extents {extents.tolist()} must be 3 finite values > 0")
    density = category_density(category, settings.density)
    fingerprint = hashlib.sha256(json.dumps({"version": IMPORT_VERSION, "box": extents.round(6).tolist(),
                                             "category": category, "density": density}).encode()).hexdigest()
    rec = reusable_record(root, asset_id, fingerprint)
    if rec is not None:
        return rec, False
    spec = box_asset(asset_id, extents, category=category, density=density,
                     role="furniture" if extents.max() > FURNITURE_EXTENT else "object")
    rec = write_asset(root, spec)
    rec.tags = ["imported", "box"]
    rec.source = {"kind": "box stand-in", "extents": extents.tolist(), "closed": True}
    write_record_sidecar(root, asset_id, fingerprint, rec)
    return rec, True


def settings_dict(settings: ImportSettings) -> dict:
    return asdict(settings)
