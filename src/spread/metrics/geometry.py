"""Point sets and signed distances shared by the mesh metrics (Col_mesh and ASD, DESIGN §6).

Frames and units: metres; an object's canonical (local) frame is its asset's canonical mesh frame,
placed in the world by ``v_world = R · v_local + t``. Distances are computed in the frame of the mesh
being measured against, so its cached acceleration structures (trimesh builds them once per mesh
object, and the library keeps one mesh object per asset) are reused for every scene.

Sign convention here: **positive outside**, negative inside (trimesh's ``signed_distance`` is the
opposite, positive inside; :func:`signed_distance_outside` flips it).

Minimum with pruning. Two lower bounds let most points go unqueried. (1) A mesh lies inside its
axis-aligned bounding box, so ``sd_mesh(p) ≥ sd_box(p)`` (the box's exact signed distance, also positive
outside): a point outside the box is at least that far from the mesh, and a point inside the mesh is no
deeper in it than in its box. (2) A signed distance is 1-Lipschitz, so ``sd(p) ≥ sd(q) − |p − q|`` for
every queried point q: points near a queried point that is far outside need no query. trimesh's signed
distance (rtree + exact closest points, ray tests for the sign) is called only on points whose bound is
below the best value found so far (less a 10 µm tolerance), in a few batches; the result is the minimum
over the point set to within that tolerance.

Meshes as shipped (open, non-manifold, self-intersecting: :mod:`spread.metrics.solid`). A mesh takes the
exact path above when it is watertight and no face of it is buried inside its own solid. Any other mesh
is measured as a *solid by winding number* (:class:`~spread.metrics.solid.SolidMesh`): inside where the
generalised winding number exceeds ½, distances to its bounding faces. Bound (1) still holds outside the
box (the mesh's faces lie in it), so points outside are skipped as before; inside the box neither bound
holds (an opening lets the inside reach the box without crossing a face), so every point inside the box
is queried, in one batch (libigl: an AABB tree and the fast winding number) — exact over the point set.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Surface samples per object: a fixed stride through the asset cache's area-weighted samples.
SURFACE_SAMPLES = 1024
#: Most mesh vertices per object (a fixed stride when a mesh has more).
MAX_VERTICES = 2048
#: Inward offsets (metres) of the surface samples tried as interior points (:func:`interior_points`), and how many
#: surface samples are offset (a fixed stride), and the most interior points kept per object.
INTERIOR_OFFSETS = (0.005, 0.01, 0.02, 0.04, 0.08, 0.16)
INTERIOR_SAMPLES = 256
MAX_INTERIOR = 1024
#: Points per first trimesh query in :func:`min_signed_distance` (the chunk doubles after each query).
FIRST_CHUNK = 64
#: Queried neighbours whose distances bound a point's signed distance (1-Lipschitz) in :func:`min_signed_distance`.
LIPSCHITZ_NEIGHBOURS = 4
#: :func:`min_signed_distance` may miss the minimum by at most this, metres (10 µm: far below the 1 cm
#: collision threshold and ASD's millimetres, above float32 pose round-off, which would otherwise make
#: every point of a face resting on another face a candidate).
DISTANCE_TOLERANCE = 1e-5


@dataclass(frozen=True)
class AssetGeometry:
    """One asset's measuring geometry, canonical frame, metres.

    mesh: the canonical mesh used for queries (trimesh.Trimesh): the library's own mesh, or a copy
        without its zero-area faces when it has some (see :func:`asset_geometry`).
    points: (P, 3) float64, the mesh vertices (at most :data:`MAX_VERTICES`) followed by surface samples
        (at most :data:`SURFACE_SAMPLES`).
    lo, hi: (3,) the mesh's axis-aligned bounding box.
    solid: None for a watertight mesh without buried faces (the exact path); else the winding-number
        solid (:class:`~spread.metrics.solid.SolidMesh`) that signed distances are measured against.
    """

    asset_id: str
    mesh: object
    points: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    solid: object = None

    @property
    def has_openings(self) -> bool:
        """Not watertight: its solid can be entered without crossing a face (through an opening)."""
        return self.solid is not None and not bool(self.mesh.is_watertight)


_GEOMETRY: dict[tuple[str, str], AssetGeometry] = {}
_FCL: dict[tuple[str, str], object] = {}


def _strided(points: np.ndarray, limit: int) -> np.ndarray:
    step = max(1, int(np.ceil(len(points) / limit)))
    return points[::step]


def asset_geometry(library, asset_id: str) -> AssetGeometry:
    """The :class:`AssetGeometry` of an asset, built once per content hash and kept for the process.

    A watertight mesh without buried faces takes the exact path; any other mesh (open, non-manifold,
    overlapping bodies) is measured as a winding-number solid (module docstring). Raises ``ValueError``
    naming the asset only when the mesh has no non-degenerate face. Zero-area faces (boolean unions leave
    a few slivers) are dropped from the query mesh: they bound no volume, but trimesh's sign test would
    take the zero normal of a sliver that happens to hold the closest point and return a distance of 0.
    """
    from spread.metrics.solid import solid_mesh

    key = (library[asset_id].content_hash, asset_id)
    geom = _GEOMETRY.get(key)
    if geom is None:
        mesh = library.mesh(asset_id)
        solid = solid_mesh(mesh, name=f"asset '{asset_id}'")
        if mesh.is_watertight and solid.buried == 0:
            solid = None
        keep = mesh.nondegenerate_faces()
        if not keep.all():
            mesh = mesh.copy()
            mesh.update_faces(keep)
        samples, _ = library.surface_points(asset_id)
        vertices = _strided(np.asarray(mesh.vertices, np.float64), MAX_VERTICES)
        points = np.concatenate([vertices, _strided(np.asarray(samples, np.float64), SURFACE_SAMPLES)])
        lo, hi = (np.asarray(b, np.float64) for b in mesh.bounds)
        geom = _GEOMETRY[key] = AssetGeometry(asset_id, mesh, points, lo, hi, solid)
    return geom


_INTERIOR: dict[tuple[str, str], np.ndarray] = {}


def interior_points(library, asset_id: str) -> np.ndarray:
    """(Q, 3) float64 points inside the asset's solid, canonical frame, metres: surface samples moved inward along
    their normals by each of :data:`INTERIOR_OFFSETS`, those whose signed distance is negative (by the measuring
    geometry's own rule: the exact mesh or the winding-number solid) — points at every depth a part of the object
    has, in thin parts (a 4 cm table top) as in thick ones — at most :data:`MAX_INTERIOR` (a fixed stride), built
    once per content hash. Col_mesh measures them beside the surface points: an object that coincides, or nearly,
    with another of the same shape has every surface point on or near the other's surface (a depth of about their
    offset, below the threshold), while its interior lies inside the other, as deep as its parts are thick."""
    key = (library[asset_id].content_hash, asset_id)
    points = _INTERIOR.get(key)
    if points is None:
        geom = asset_geometry(library, asset_id)
        samples, normals = library.surface_points(asset_id)
        step = max(1, int(np.ceil(len(samples) / INTERIOR_SAMPLES)))
        samples = np.asarray(samples, np.float64)[::step]
        normals = np.asarray(normals, np.float64)[::step]
        candidates = np.concatenate([samples - offset * normals for offset in INTERIOR_OFFSETS])
        d = geom.solid.signed_distance(candidates) if geom.solid is not None else \
            signed_distance_outside(geom.mesh, candidates)
        points = _INTERIOR[key] = _strided(candidates[d < -DISTANCE_TOLERANCE], MAX_INTERIOR)
    return points


def fcl_geometry(library, asset_id: str):
    """The asset's python-fcl collision geometry, built once per content hash: ``fcl.Convex`` for a convex
    mesh, else a ``fcl.BVHModel`` (the same choice and builders as ``trimesh.collision.CollisionManager``)."""
    key = (library[asset_id].content_hash, asset_id)
    geom = _FCL.get(key)
    if geom is None:
        from trimesh.collision import mesh_to_BVH, mesh_to_convex

        mesh = library.mesh(asset_id)
        geom = _FCL[key] = mesh_to_convex(mesh) if mesh.is_convex else mesh_to_BVH(mesh)
    return geom


def to_local(points_world: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """World points (P, 3) → the local frame of an object posed by (R, t): ``Rᵀ (p − t)``."""
    return (np.asarray(points_world, np.float64) - translation) @ rotation


def to_world(points_local: np.ndarray, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Local points (P, 3) → world: ``R p + t``."""
    return np.asarray(points_local, np.float64) @ rotation.T + translation


def box_signed_distance(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(P,) exact signed distance (positive outside) of points (P, 3) to the box [lo, hi], metres."""
    q = np.maximum(lo - points, points - hi)  # per-axis distance outside the slab (negative inside)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=1)
    return outside + np.minimum(q.max(axis=1), 0.0)


def signed_distance_outside(mesh, points: np.ndarray) -> np.ndarray:
    """(P,) signed distance of points (P, 3) to a watertight mesh, **positive outside**, metres."""
    from trimesh.proximity import signed_distance

    return -np.asarray(signed_distance(mesh, points), np.float64)


def min_signed_distance(geom: AssetGeometry, points_local: np.ndarray, stop_at: float = np.inf,
                        tolerance: float = DISTANCE_TOLERANCE) -> tuple[float, int]:
    """Smallest signed distance (positive outside) of points (P, 3), given in ``geom``'s local frame, to
    ``geom.mesh``, and the index of the point that attains it (module docstring).

    ``stop_at``: values above it are not needed (the caller clips them). A point is queried only while
    its lower bound is below ``min(best, stop_at) − tolerance``, so the result is within ``tolerance`` of
    the exact minimum over the point set (when that is below ``stop_at``); (inf, −1) when no point needed
    a query. The first query takes a spread-out subset; later ones the points with the smallest bounds.
    """
    from scipy.spatial import cKDTree

    n = len(points_local)
    bound = box_signed_distance(points_local, geom.lo, geom.hi)
    if geom.solid is not None:  # winding-number solid: only bound (1) outside the box holds
        best, best_index = float("inf"), -1
        inside_box = bound <= 0
        for todo in (np.flatnonzero(inside_box), None):
            if todo is None:  # then the points outside the box that could still be lower
                todo = np.flatnonzero(~inside_box & (bound < min(best, stop_at) - tolerance))
            if len(todo):
                d = geom.solid.signed_distance(points_local[todo])
                k = int(np.argmin(d))
                if d[k] < best:
                    best, best_index = float(d[k]), int(todo[k])
        return best, best_index
    value = np.full(n, np.inf)
    done = np.zeros(n, bool)
    best, best_index, chunk = float("inf"), -1, FIRST_CHUNK
    while True:
        cutoff = min(best, stop_at) - tolerance
        todo = np.flatnonzero(~done & (bound < cutoff))
        if len(todo) and done.any():  # Lipschitz: sd(p) ≥ sd(q) − |p − q| for each queried q
            queried = np.flatnonzero(done)
            k = min(LIPSCHITZ_NEIGHBOURS, len(queried))
            dist, near = cKDTree(points_local[queried]).query(points_local[todo], k=k)
            lipschitz = (value[queried][near.reshape(len(todo), k)] - dist.reshape(len(todo), k)).max(1)
            bound[todo] = np.maximum(bound[todo], lipschitz)
            todo = todo[bound[todo] < cutoff]
        if len(todo) == 0:
            return best, best_index
        if done.any():
            pick = todo[np.argsort(bound[todo], kind="stable")[:chunk]]
        else:
            pick = todo[np.linspace(0, len(todo) - 1, min(chunk, len(todo))).astype(np.int64)]
        d = signed_distance_outside(geom.mesh, points_local[pick])
        value[pick], done[pick] = d, True
        k = int(np.argmin(d))
        if d[k] < best:
            best, best_index = float(d[k]), int(pick[k])
        chunk *= 2
