"""Spatial relation codes (DESIGN §3) — the one implementation used by data, GRecall and Stability.

``spatial_codes(aabb_min, aabb_max)[i, j]`` says "i is <code> of j", from each object's world
axis-aligned bounding box (AABB) of its posed mesh:

* horizontal sector from θ = atan2(dz, dx) of the AABB centres' difference c_i − c_j:
  right of −π/4 ≤ θ < π/4; in front of π/4 ≤ θ < 3π/4; behind −3π/4 ≤ θ < −π/4; left of otherwise;
* vertical override when the xz-centre of either lies inside the other's xz footprint (the AABB's xz
  rectangle, boundary included) and they do not overlap vertically beyond
  :data:`VERTICAL_TOLERANCE` (i's bottom ≥ j's top − 5 mm: above; i's top ≤ j's bottom + 5 mm: below).

Everything is vectorised over all ordered pairs (numpy, or torch when given tensors).

Physical codes (support / contact) come from :func:`physical_codes` below, computed on posed meshes:
see its docstring for the rule.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from spread.scene import (
    SPATIAL_ABOVE, SPATIAL_BEHIND, SPATIAL_BELOW, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT, SPATIAL_SELF,
)

#: Vertical overlap (metres) still counted as "above"/"below" (an object resting on another touches it).
VERTICAL_TOLERANCE = 0.005


def spatial_codes(aabb_min, aabb_max):
    """(N, N) int8 spatial codes from world AABBs (N, 3) min and max, metres, y-up.

    Accepts numpy arrays (returns numpy) or torch tensors of shape (..., N, 3) (returns a torch
    int8 tensor of shape (..., N, N)); torch is used by the model side for batched scenes. One body for both:
    only the array constructors differ (:func:`_array_ops`).
    """
    ops = _array_ops(aabb_min)
    lo, hi = ops.float64(aabb_min), ops.float64(aabb_max)
    if tuple(lo.shape) != tuple(hi.shape) or lo.shape[-1] != 3:
        raise ValueError(f"spatial_codes: aabb_min {tuple(lo.shape)} and aabb_max {tuple(hi.shape)} must both be "
                         f"(..., N, 3)")
    c = 0.5 * (lo + hi)
    d = c[..., :, None, :] - c[..., None, :, :]  # c_i − c_j
    theta = ops.atan2(d[..., 2], d[..., 0])
    codes = ops.full_int8(theta, SPATIAL_LEFT)
    q = math.pi / 4
    codes[(theta >= -q) & (theta < q)] = SPATIAL_RIGHT
    codes[(theta >= q) & (theta < 3 * q)] = SPATIAL_FRONT
    codes[(theta >= -3 * q) & (theta < -q)] = SPATIAL_BEHIND

    cx, cz = c[..., 0], c[..., 2]
    # centre of i inside footprint of j
    i_in_j = ((cx[..., :, None] >= lo[..., None, :, 0]) & (cx[..., :, None] <= hi[..., None, :, 0])
              & (cz[..., :, None] >= lo[..., None, :, 2]) & (cz[..., :, None] <= hi[..., None, :, 2]))
    stacked = i_in_j | ops.swap_last(i_in_j)
    above = lo[..., :, None, 1] >= hi[..., None, :, 1] - VERTICAL_TOLERANCE
    below = hi[..., :, None, 1] <= lo[..., None, :, 1] + VERTICAL_TOLERANCE
    codes[stacked & above] = SPATIAL_ABOVE
    codes[stacked & below & ~above] = SPATIAL_BELOW
    idx = ops.arange(codes)
    codes[..., idx, idx] = SPATIAL_SELF
    return codes


class _Ops(NamedTuple):
    float64: object
    atan2: object
    full_int8: object
    swap_last: object
    arange: object


def _array_ops(example) -> _Ops:
    """The few constructors :func:`spatial_codes` needs, for numpy arrays or (lazily imported) torch tensors."""
    if isinstance(example, np.ndarray) or not hasattr(example, "double"):
        return _Ops(lambda a: np.asarray(a, np.float64), np.arctan2,
                    lambda like, v: np.full(like.shape, v, dtype=np.int8), lambda a: np.swapaxes(a, -1, -2),
                    lambda codes: np.arange(codes.shape[-1]))
    import torch

    return _Ops(lambda a: a.double(), torch.atan2,
                lambda like, v: torch.full(like.shape, v, dtype=torch.int8, device=like.device),
                lambda a: a.transpose(-1, -2), lambda codes: torch.arange(codes.shape[-1], device=codes.device))


def posed_aabbs(translation: np.ndarray, rotation: np.ndarray, local_vertices: list[np.ndarray]):
    """World AABBs (N, 3) min and max of posed point sets.

    ``local_vertices[i]`` are canonical-frame points of object i (pass the convex-hull vertices: a
    mesh's AABB equals its hull's, and hulls are much smaller).
    """
    n = len(local_vertices)
    lo = np.empty((n, 3))
    hi = np.empty((n, 3))
    for i, v in enumerate(local_vertices):
        w = np.asarray(v, np.float64) @ np.asarray(rotation[i], np.float64).T + np.asarray(translation[i], np.float64)
        lo[i], hi[i] = w.min(0), w.max(0)
    return lo, hi


# ==================================================================================================
# Physical relations: support and contact from posed geometry
# ==================================================================================================

#: A surface sample closer than this (metres) to another object's surface counts as touching it.
CONTACT_TOLERANCE = 0.003
#: A sample faces down (can rest on something) when its world normal's y is below this.
DOWNWARD_NORMAL_Y = -0.3
#: Fewest touching downward samples for a support relation (guards against grazing contacts).
MIN_SUPPORT_SAMPLES = 3
#: Samples per object used for contact detection (a subset of the asset cache's surface samples).
CONTACT_SAMPLES = 768


def part_planes(parts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Face planes of convex parts in their own frame: unit normals (F, 3), offsets (F,), part start
    indices (n_parts,). A point p is inside part k iff ``max_f(n_f·p − d_f) ≤ 0`` over its planes.
    Coplanar triangles are merged, so a box has 6 planes.
    """
    normals, offsets, starts = [], [], []
    count = 0
    for part in parts:
        n = np.asarray(part.face_normals, np.float64)
        d = np.einsum("fk,fk->f", n, np.asarray(part.triangles_center, np.float64))
        key = np.round(np.concatenate([n, d[:, None]], axis=1), 7)
        _, keep = np.unique(key, axis=0, return_index=True)
        keep.sort()
        starts.append(count)
        normals.append(n[keep])
        offsets.append(d[keep])
        count += len(keep)
    return np.concatenate(normals), np.concatenate(offsets), np.asarray(starts, np.int64)


def signed_distance_to_parts(points: np.ndarray, normals: np.ndarray, offsets: np.ndarray,
                             starts: np.ndarray) -> np.ndarray:
    """Signed distance proxy (metres, negative inside) of points (P, 3) to a union of convex parts.

    Per part it is the largest plane distance ``max_f(n_f·p − d_f)``: exact for points inside a part
    and for points outside whose nearest feature is a face; it underestimates the distance to edges
    and corners by at most a factor √3. That is what contact detection needs (a point within a few
    millimetres of a face), and it costs one matrix product.
    """
    s = points @ normals.T - offsets  # (P, F)
    per_part = np.maximum.reduceat(s, starts, axis=1)  # (P, n_parts)
    return per_part.min(axis=1)


def posed_planes(planes, rotation: np.ndarray, translation: np.ndarray):
    """Planes of :func:`part_planes` moved by ``v ↦ R v + t``."""
    normals, offsets, starts = planes
    wn = normals @ np.asarray(rotation, np.float64).T
    return wn, offsets + wn @ np.asarray(translation, np.float64), starts


class PhysicalRelations(NamedTuple):
    """Result of :func:`physical_codes` (all (N, N) matrices indexed [i, j], i the other object of j)."""

    codes: np.ndarray  # int8 physical codes, [i, j] = 1 when i supports j, 2 contact
    floor_supported: np.ndarray  # (N,) bool, j rests on the floor
    support_samples: np.ndarray  # int, j's downward samples touching i
    min_distance: np.ndarray  # float, smallest signed distance of j's samples to i (metres; <0 penetrates; inf when far)


def physical_codes(translation: np.ndarray, rotation: np.ndarray, asset_ids, library,
                   contact_tolerance: float = CONTACT_TOLERANCE, samples: int = CONTACT_SAMPLES) -> PhysicalRelations:
    """Support and contact codes (N, N) int8 of a posed scene, plus per-object floor support.

    Rule: object i *supports* j when at least :data:`MIN_SUPPORT_SAMPLES` of j's downward-facing
    surface samples (world normal y < :data:`DOWNWARD_NORMAL_Y`) lie within ``contact_tolerance`` of
    i's surface (i's convex parts, :func:`signed_distance_to_parts`, penetration included). When j
    rests on several objects, the one touching the most samples is its supporter and the others are
    contacts, so the support graph is a forest. Any other pair with touching samples either way is a
    *contact* (code 2, both directions). An object is floor-supported when
    its lowest point is within the tolerance of y = 0; the floor is then its supporter. Returns a :class:`PhysicalRelations`.
    """
    n = len(asset_ids)
    translation = np.asarray(translation, np.float64)
    rotation = np.asarray(rotation, np.float64)
    pts, nrm, planes = [], [], []
    lo = np.empty((n, 3))
    hi = np.empty((n, 3))
    for i, aid in enumerate(asset_ids):
        p, q = library.surface_points(aid)
        step = max(1, len(p) // samples)
        R, t = rotation[i], translation[i]
        pts.append(p[::step].astype(np.float64) @ R.T + t)
        nrm.append(q[::step].astype(np.float64) @ R.T)
        hv = hull_vertices(library, aid) @ R.T + t
        lo[i], hi[i] = hv.min(0), hv.max(0)
        planes.append(posed_planes(asset_planes(library, aid), R, t))
    tol = contact_tolerance
    near = np.all((lo[:, None, :] <= hi[None, :, :] + tol) & (hi[:, None, :] >= lo[None, :, :] - tol), axis=-1)
    np.fill_diagonal(near, False)
    support_samples = np.zeros((n, n), np.int64)
    touching = np.zeros((n, n), bool)
    min_distance = np.full((n, n), np.inf)
    for i, j in zip(*np.nonzero(near)):
        d = signed_distance_to_parts(pts[j], *planes[i])  # j's samples against i
        min_distance[i, j] = d.min()
        close = d <= tol
        if close.any():
            touching[i, j] = True
            support_samples[i, j] = int(np.count_nonzero(close & (nrm[j][:, 1] < DOWNWARD_NORMAL_Y)))
    # the floor is a plane: an object whose lowest point is within the tolerance of y = 0 stands on it
    # (legs of a sofa are too small for a sample count)
    floor_supported = lo[:, 1] <= tol
    floor_samples = np.where(floor_supported, np.iinfo(np.int64).max, 0)
    codes = np.zeros((n, n), np.int8)
    contact = touching | touching.T
    codes[contact] = 2
    for j in range(n):
        if floor_supported[j] and floor_samples[j] >= support_samples[:, j].max(initial=0):
            continue
        best = int(np.argmax(support_samples[:, j])) if n else 0
        if support_samples[best, j] >= MIN_SUPPORT_SAMPLES:
            codes[best, j] = 1
            if codes[j, best] != 1:
                codes[j, best] = 0
    # a pair can't support each other: keep the direction with more touching samples
    mutual = (codes == 1) & (codes.T == 1)
    for i, j in zip(*np.nonzero(np.triu(mutual))):
        lower, upper = (i, j) if support_samples[i, j] >= support_samples[j, i] else (j, i)
        codes[upper, lower] = 2
    return PhysicalRelations(codes, floor_supported, support_samples, min_distance)


_PLANE_CACHE: dict[tuple[str, str], tuple] = {}
_HULL_CACHE: dict[tuple[str, str], np.ndarray] = {}


def asset_planes(library, asset_id: str):
    """Face planes (:func:`part_planes`) of an asset's convex parts, cached per content hash."""
    key = (library[asset_id].content_hash, asset_id)
    if key not in _PLANE_CACHE:
        _PLANE_CACHE[key] = part_planes(library.convex_parts(asset_id))
    return _PLANE_CACHE[key]


def hull_vertices(library, asset_id: str) -> np.ndarray:
    """Canonical-frame vertices of the mesh's convex hull (same AABB under any rotation, fewer points)."""
    key = (library[asset_id].content_hash, asset_id)
    if key not in _HULL_CACHE:
        _HULL_CACHE[key] = np.asarray(library.mesh(asset_id).convex_hull.vertices, np.float64)
    return _HULL_CACHE[key]


def scene_aabbs(translation: np.ndarray, rotation: np.ndarray, asset_ids, library):
    """World AABBs (N, 3) min, max of the posed meshes of a scene."""
    return posed_aabbs(translation, rotation, [hull_vertices(library, a) for a in asset_ids])


def scene_spatial_codes(translation: np.ndarray, rotation: np.ndarray, asset_ids, library) -> np.ndarray:
    """Spatial codes of a posed scene: :func:`spatial_codes` of its posed mesh AABBs."""
    return spatial_codes(*scene_aabbs(translation, rotation, asset_ids, library))
