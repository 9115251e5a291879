"""Asset library on disk: ``index.json`` + one glb mesh and one convex-parts file per asset + caches.

Layout of a library folder (DESIGN §4)::

    index.json                      {"version", "build", "assets": {asset_id: AssetRecord as dict}}
    meshes/<asset_id>.glb           visual mesh: watertight union of the convex parts
    parts/<asset_id>.npz            the convex parts (exact physics collision shapes)
    cache/<asset_id>.<hash>.npz     surface points + normals, xz hull; rebuilt when the hash changes
    records/<asset_id>.json         per-asset record + spec fingerprint, so a rebuild can resume

Frames and units: every mesh is in the asset's *canonical* frame — metres, y-up, centred at the
centre of its axis-aligned bounding box (so its bbox is ``[-extents/2, +extents/2]``). A placed object
is ``v_world = R · v_local + t``.

Records carry what placement and physics need: category, extents, volume, density, mass, the stable
rest poses (rotations that put the asset on a flat surface), and for furniture the horizontal support
surfaces (table tops, shelf levels) objects can be placed on.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Iterator, Sequence

import numpy as np

from spread.io import atomic_path, read_json, read_json_object, write_json_atomic

LIBRARY_VERSION = 1
#: Surface samples stored per asset in its cache (the issue asks for at least 2,000).
CACHE_SURFACE_POINTS = 4096


class AssetError(KeyError):
    """An asset id is unknown or an asset's files are broken; the message names them."""

    def __str__(self) -> str:  # KeyError quotes its message; keep it readable
        return str(self.args[0]) if self.args else ""


class AssetFileError(AssetError, ValueError):
    """An asset's file does not read (a truncated or foreign mesh): a bad input, named in one line by a command."""


@dataclass
class SupportSurface:
    """A horizontal surface objects can rest on, in the asset's canonical frame (metres, y-up).

    ``height`` is the local y of the surface (top face of a table top or shelf board); the usable
    region is the rectangle ``xz_min .. xz_max`` in local x, z; ``clearance`` is the free height above
    it (the gap to the next shelf board), ``inf`` for an open top. ``kind`` says what the surface is:
    "top" (table/counter/cabinet top, top of a book or box), "shelf" (a shelf level under another
    board), "seat" (sofa, chair, stool seat), "bed" (mattress top) or "inside" (the floor of a bowl,
    tray or basket: a container's inside; a plate's floor is a "top").
    """

    height: float
    xz_min: tuple[float, float]
    xz_max: tuple[float, float]
    clearance: float = float("inf")
    kind: str = "top"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["clearance"] = None if not np.isfinite(self.clearance) else float(self.clearance)
        d["xz_min"], d["xz_max"] = [float(v) for v in self.xz_min], [float(v) for v in self.xz_max]
        d["height"] = float(self.height)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "SupportSurface":
        return cls(
            height=float(d["height"]), xz_min=tuple(d["xz_min"]), xz_max=tuple(d["xz_max"]),
            clearance=float("inf") if d.get("clearance") is None else float(d["clearance"]),
            kind=str(d.get("kind", "top")),
        )


@dataclass
class RestPose:
    """A stable resting orientation.

    ``rotation`` (3×3, world-from-local) puts the canonical mesh on its resting face; any further yaw
    about world y keeps it stable. ``bottom_offset`` is the distance from the object's origin (bbox
    centre) down to its lowest point after ``rotation``: on a surface at height h the origin sits at
    y = h + bottom_offset. ``weight`` is the relative probability of sampling this pose.
    """

    name: str
    rotation: np.ndarray
    bottom_offset: float
    weight: float = 1.0

    def to_dict(self) -> dict:
        return {
            "name": self.name, "rotation": np.asarray(self.rotation, float).round(12).tolist(),
            "bottom_offset": float(self.bottom_offset), "weight": float(self.weight),
        }

    @classmethod
    def from_dict(cls, d: dict) -> "RestPose":
        return cls(name=d["name"], rotation=np.asarray(d["rotation"], dtype=np.float64),
                   bottom_offset=float(d["bottom_offset"]), weight=float(d.get("weight", 1.0)))


@dataclass
class AssetRecord:
    """Everything known about one asset without loading its mesh."""

    asset_id: str
    category: str
    variant: int
    role: str  # "furniture" (stands on the floor) or "object" (small, placed on surfaces)
    extents: np.ndarray  # (3,) canonical bbox size, metres
    volume: float  # m³ of the watertight mesh
    density: float  # kg/m³ of the category (effective, hollow objects are lighter)
    mass: float  # kg = volume × density
    mesh_file: str  # relative to the library root
    parts_file: str
    num_parts: int
    num_faces: int
    content_hash: str  # sha256 of mesh + parts files; keys the caches
    rest_poses: list[RestPose] = field(default_factory=list)
    support_surfaces: list[SupportSurface] = field(default_factory=list)
    tags: list[str] = field(default_factory=list)  # e.g. "stackable", "container"
    #: where an imported asset came from and what was done to it (file, sha256, cleaning, decomposition
    #: and its fidelity); empty for procedural assets. Stored in index.json only when not empty.
    source: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = {
            "asset_id": self.asset_id, "category": self.category, "variant": int(self.variant),
            "role": self.role, "extents": [float(v) for v in self.extents], "volume": float(self.volume),
            "density": float(self.density), "mass": float(self.mass), "mesh_file": self.mesh_file,
            "parts_file": self.parts_file, "num_parts": int(self.num_parts), "num_faces": int(self.num_faces),
            "content_hash": self.content_hash,
            "rest_poses": [p.to_dict() for p in self.rest_poses],
            "support_surfaces": [s.to_dict() for s in self.support_surfaces],
            "tags": list(self.tags),
        }
        if self.source:
            d["source"] = dict(self.source)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "AssetRecord":
        for key in ("mesh_file", "parts_file"):
            inside_library(key, d[key])
        check_measures(d)
        return cls(
            asset_id=d["asset_id"], category=d["category"], variant=int(d["variant"]), role=d["role"],
            extents=np.asarray(d["extents"], dtype=np.float64), volume=float(d["volume"]),
            density=float(d["density"]), mass=float(d["mass"]), mesh_file=d["mesh_file"],
            parts_file=d["parts_file"], num_parts=int(d["num_parts"]), num_faces=int(d["num_faces"]),
            content_hash=d["content_hash"],
            rest_poses=[RestPose.from_dict(p) for p in d.get("rest_poses", [])],
            support_surfaces=[SupportSurface.from_dict(s) for s in d.get("support_surfaces", [])],
            tags=list(d.get("tags", [])), source=dict(d.get("source") or {}),
        )


def check_measures(d: dict) -> None:
    """``ValueError`` naming the key and value of a record's measure that no physics, statistic or model can use:
    ``extents`` not three finite numbers > 0 (metres), ``mass`` not a finite number > 0 (kg), ``volume`` or
    ``density`` not finite and ≥ 0 (a NaN mass made pybullet's world wrong for every later scene of its worker; a
    NaN extent on an unused asset made a baseline's size bounds, and every weight, NaN)."""
    import math

    def number(value) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

    extents = d.get("extents")
    if not (isinstance(extents, (list, tuple)) and len(extents) == 3 and all(number(v) and v > 0 for v in extents)):
        raise ValueError(f"extents={extents!r}: expected three finite sizes > 0 (metres)")
    if not (number(d.get("mass")) and d["mass"] > 0):
        raise ValueError(f"mass={d.get('mass')!r}: expected a finite number of kg > 0")
    for key in ("volume", "density"):
        if not (number(d.get(key)) and d[key] >= 0):
            raise ValueError(f"{key}={d.get(key)!r}: expected a finite number ≥ 0")


def inside_library(key: str, value) -> str:
    """A record's file (``mesh_file``, ``parts_file``) as a relative path that stays inside the library's folder:
    ``ValueError`` naming the key and value for an absolute path, a ``..`` step, a backslash or an empty name (an
    index must not make the library read files of another tree)."""
    from pathlib import PurePosixPath

    text = value if isinstance(value, str) else ""
    if not text or "\\" in text or PurePosixPath(text).is_absolute() or ".." in PurePosixPath(text).parts:
        raise ValueError(f"{key}={value!r}: not a relative path inside the library (no absolute path, '..' or '\\')")
    return text


def _sidecar(root: Path, asset_id: str) -> Path:
    return Path(root) / "records" / f"{asset_id}.json"


def reusable_record(root: str | os.PathLike, asset_id: str, fingerprint: str) -> AssetRecord | None:
    """The asset's recorded :class:`AssetRecord` when its sidecar ``records/<asset_id>.json`` was written for
    ``fingerprint`` (what built it: spec, source file, settings) and its mesh and parts files are intact; else
    None (the asset is to be built again)."""
    from spread.io import file_sha256

    try:
        data = read_json(_sidecar(Path(root), asset_id))
        if data.get("fingerprint", data.get("spec_fingerprint")) != fingerprint:  # spec_…: older libraries
            return None
        rec = AssetRecord.from_dict(data["record"])
        if file_sha256(Path(root) / rec.mesh_file, Path(root) / rec.parts_file) != rec.content_hash:
            return None
        return rec
    except (OSError, ValueError, KeyError, TypeError):
        return None


def write_record_sidecar(root: str | os.PathLike, asset_id: str, fingerprint: str, rec: AssetRecord) -> None:
    """``records/<asset_id>.json``: the record and the fingerprint it was built for (atomic)."""
    write_json_atomic(_sidecar(Path(root), asset_id), {"fingerprint": fingerprint, "record": rec.to_dict()})


@dataclass
class AssetGeometryCache:
    """Per-asset derived data, canonical frame. Points/normals float32 (P, 3); hull (K, 2) CCW in xz."""

    surface_points: np.ndarray
    surface_normals: np.ndarray
    xz_hull: np.ndarray


# --------------------------------------------------------------------------------------------------
# parts files
# --------------------------------------------------------------------------------------------------

def parts_bytes(parts: Sequence["object"]) -> bytes:
    """Convex parts (trimesh.Trimesh each) as npz bytes: concatenated vertices/faces + counts.

    Byte-identical for identical parts (fixed zip timestamps), so a rebuild keeps the content hash.
    """
    import io
    import zipfile

    verts = [np.asarray(p.vertices, np.float64) for p in parts]
    faces = [np.asarray(p.faces, np.int32) for p in parts]
    arrays = {
        "vertices": np.concatenate(verts).astype(np.float64),
        "faces": np.concatenate(faces).astype(np.int32),
        "vertex_counts": np.array([len(v) for v in verts], np.int64),
        "face_counts": np.array([len(f) for f in faces], np.int64),
    }
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with zf.open(info, "w") as fh:
                np.lib.format.write_array(fh, arr, allow_pickle=False)
    return buf.getvalue()


def save_parts(path: str | os.PathLike, parts: Sequence["object"]) -> None:
    """Write convex parts as one npz (see :func:`parts_bytes`), atomically."""
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(parts_bytes(parts))


def load_parts(path: str | os.PathLike) -> list["object"]:
    import trimesh

    from spread.safe_load import load_npz

    with load_npz(path) as data:
        V, F = data["vertices"], data["faces"]
        vc, fc = data["vertex_counts"], data["face_counts"]
    out, vo, fo = [], 0, 0
    for nv, nf in zip(vc, fc):
        out.append(trimesh.Trimesh(V[vo:vo + nv], F[fo:fo + nf], process=False))
        vo += int(nv)
        fo += int(nf)
    return out


# --------------------------------------------------------------------------------------------------
# the library
# --------------------------------------------------------------------------------------------------

class AssetLibrary:
    """Read access to a library folder, with in-memory caches of meshes, parts and geometry caches.

    Thread-safe for reads. Cheap to construct (reads only ``index.json``); meshes load on first use.
    """

    def __init__(self, root: str | os.PathLike, records: dict[str, AssetRecord]):
        self.root = Path(root)
        self.records = records
        self._lock = threading.Lock()
        self._meshes: dict[str, object] = {}
        self._parts: dict[str, list] = {}
        self._geometry: dict[str, AssetGeometryCache] = {}

    # ---- loading -----------------------------------------------------------------------------
    @classmethod
    def load(cls, root: str | os.PathLike) -> "AssetLibrary":
        root = Path(root)
        index = root / "index.json"
        if not index.exists():
            raise FileNotFoundError(f"{index}: no asset library here (missing index.json)")
        data = read_json_object(index)
        if data.get("version") != LIBRARY_VERSION:
            raise ValueError(f"{index}: key 'version' is {data.get('version')!r}, expected {LIBRARY_VERSION}")
        records = {}
        for aid, d in data.get("assets", {}).items():
            try:
                records[aid] = AssetRecord.from_dict(d)
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"{index}: asset '{aid}' has a bad record ({type(exc).__name__}: {exc})") from exc
        return cls(root, records)

    def save_index(self, build: dict | None = None) -> None:
        """Write ``index.json`` atomically; ``build`` (seed, variants, ...) is stored under "build"."""
        data = {"version": LIBRARY_VERSION}
        if build is not None:
            data["build"] = build
        data["assets"] = {aid: rec.to_dict() for aid, rec in sorted(self.records.items())}
        write_json_atomic(self.root / "index.json", data)

    # ---- lookup ------------------------------------------------------------------------------
    def __contains__(self, asset_id: object) -> bool:
        return asset_id in self.records

    def __getitem__(self, asset_id: str) -> AssetRecord:
        try:
            return self.records[asset_id]
        except KeyError:
            raise AssetError(f"unknown asset '{asset_id}' (library {self.root})") from None

    def __iter__(self) -> Iterator[str]:
        return iter(sorted(self.records))

    def __len__(self) -> int:
        return len(self.records)

    @property
    def categories(self) -> list[str]:
        return sorted({r.category for r in self.records.values()})

    def ids_of(self, category: str) -> list[str]:
        return sorted(a for a, r in self.records.items() if r.category == category)

    # ---- geometry ----------------------------------------------------------------------------
    def mesh(self, asset_id: str):
        """The canonical visual mesh (trimesh.Trimesh). Do not modify it in place: copy first."""
        rec = self[asset_id]
        with self._lock:
            if asset_id not in self._meshes:
                import trimesh

                path = self.root / rec.mesh_file
                if not path.exists():
                    raise AssetError(f"{path}: mesh file of asset '{asset_id}' is missing")
                from spread.io import check_input_file

                try:
                    m = trimesh.load(check_input_file(path, root=self.root), force="mesh", process=False)
                    mesh = trimesh.Trimesh(m.vertices, m.faces, process=False)
                except AssetError:
                    raise
                except Exception as exc:  # noqa: BLE001 - a truncated or foreign file: trimesh's errors name neither
                    raise AssetFileError(f"{path}: mesh file of asset '{asset_id}' does not read as a mesh "
                                     f"({type(exc).__name__}: {exc})") from None
                self._meshes[asset_id] = mesh
            return self._meshes[asset_id]

    def convex_parts(self, asset_id: str) -> list:
        """The convex parts (trimesh.Trimesh each) in the canonical frame: the physics shapes."""
        rec = self[asset_id]
        with self._lock:
            if asset_id not in self._parts:
                path = self.root / rec.parts_file
                if not path.exists():
                    raise AssetError(f"{path}: parts file of asset '{asset_id}' is missing")
                self._parts[asset_id] = load_parts(path)
            return self._parts[asset_id]

    def cache_path(self, asset_id: str) -> Path:
        """``cache/<asset_id>.<hash>.npz`` as one :func:`spread.io.safe_name` inside the library, whatever
        the index says the id or hash is."""
        from spread.io import safe_name

        rec = self[asset_id]
        return self.root / "cache" / (safe_name(f"{asset_id}.{str(rec.content_hash)[:16]}") + ".npz")

    def geometry(self, asset_id: str) -> AssetGeometryCache:
        """Surface points/normals and xz hull, built once per content hash and kept on disk."""
        with self._lock:
            hit = self._geometry.get(asset_id)
        if hit is not None:
            return hit
        path = self.cache_path(asset_id)
        cache = None
        if path.exists():
            try:
                from spread.safe_load import load_npz

                with load_npz(path) as d:
                    cache = AssetGeometryCache(d["surface_points"], d["surface_normals"], d["xz_hull"])
            except Exception:
                cache = None  # torn or stale cache: rebuild
            if cache is not None and cache_problem(cache) is not None:
                import logging

                logging.getLogger("spread.assets").warning("%s: %s; rebuilt from the mesh", path, cache_problem(cache))
                cache = None  # a damaged cache (NaN points, other shapes or counts): rebuilt, never trained on
        if cache is None:
            cache = build_geometry_cache(self.mesh(asset_id), seed=_stable_seed(asset_id))
            with atomic_path(path) as tmp, open(tmp, "wb") as fh:
                np.savez(fh, surface_points=cache.surface_points, surface_normals=cache.surface_normals,
                         xz_hull=cache.xz_hull)
        with self._lock:
            self._geometry[asset_id] = cache
        return cache

    def surface_points(self, asset_id: str) -> tuple[np.ndarray, np.ndarray]:
        g = self.geometry(asset_id)
        return g.surface_points, g.surface_normals

    def build_caches(self, asset_ids: Iterable[str] | None = None) -> int:
        """Build every missing cache; returns how many were built."""
        built = 0
        for aid in (asset_ids or list(self)):
            if not self.cache_path(aid).exists():
                built += 1
            self.geometry(aid)
        return built


def cache_problem(cache: AssetGeometryCache) -> str | None:
    """What makes a geometry cache read from disk other than :func:`build_geometry_cache` writes it (None: sound):
    points and normals (CACHE_SURFACE_POINTS, 3) of finite numbers, a hull (K ≥ 3, 2) of finite numbers."""
    for key, value, shape in (("surface_points", cache.surface_points, (CACHE_SURFACE_POINTS, 3)),
                              ("surface_normals", cache.surface_normals, (CACHE_SURFACE_POINTS, 3))):
        if not isinstance(value, np.ndarray) or value.shape != shape or value.dtype.kind != "f":
            return f"key '{key}' is not ({shape[0]}, 3) numbers"
        if not np.isfinite(value).all():
            return f"key '{key}' holds non-finite numbers"
    hull = cache.xz_hull
    if not (isinstance(hull, np.ndarray) and hull.ndim == 2 and hull.shape[0] >= 3 and hull.shape[1] == 2
            and hull.dtype.kind == "f" and np.isfinite(hull).all()):
        return "key 'xz_hull' is not (K ≥ 3, 2) finite numbers"
    return None


def build_geometry_cache(mesh, n_points: int = CACHE_SURFACE_POINTS, seed: int = 0) -> AssetGeometryCache:
    """Area-weighted surface samples with face normals, and the CCW xz convex hull of the vertices."""
    import trimesh
    from scipy.spatial import ConvexHull

    pts, face_idx = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    normals = np.asarray(mesh.face_normals)[face_idx]
    xz = np.asarray(mesh.vertices)[:, [0, 2]]
    hull = ConvexHull(xz)
    hull_xz = xz[hull.vertices]  # scipy returns 2D hull vertices counter-clockwise
    return AssetGeometryCache(pts.astype(np.float32), normals.astype(np.float32), hull_xz.astype(np.float32))


def _stable_seed(text: str) -> int:
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little")
