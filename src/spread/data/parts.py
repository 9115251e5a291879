"""Per-asset convex part planes for the ``parts`` geometry distance (:mod:`spread.model.parts_distance`).

An asset is the union of its convex parts (DESIGN §3: the physics shapes; for the generated assets the visual mesh
is exactly their boolean union). A convex part is the intersection of the half-spaces of its face planes, so a
point p (asset frame, metres) is inside the part iff every ``n·p − d`` is negative, and

    s_part(p) = max over the part's planes of (n·p − d)

is minus the depth of p inside the part (exact inside), and outside a lower bound of its distance to the part.
``min`` over the parts gives the asset's signed distance with the exact sign — what the release's signed chamfer
proxy (nearest sampled point, signed by its normal) cannot tell on furniture made of boards.

The batch carries, per object, ``part_planes`` (P, F, 4) = [n (unit), d], ``part_boxes`` (P, 2, 3) the part's
canonical axis-aligned box (min, max: to skip far parts) and ``part_valid`` (P,) bool, with the caps
``PART_CAP`` parts × ``FACE_CAP`` planes: a part with fewer planes repeats its first (a max is unchanged by a
repeat); a part with more keeps ``FACE_CAP`` of them spread over its normals (farthest-point order: a slightly
larger polytope round a many-sided part, e.g. an ellipsoid's hull); an asset with more parts keeps its
``PART_CAP`` largest by volume. :func:`mirror_planes` gives the mirrored asset's (floor symmetries with a mirror).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

#: Most parts per object the batch carries (the generated library's assets have ≤ 23).
PART_CAP = 32
#: Most planes per part (boxes have 6, the 16-sided prisms 18).
FACE_CAP = 24
#: ``ModelConfig.geometry_distance``, the one list: ``chamfer`` (the release's signed nearest-point proxy,
#: :mod:`spread.model.geometry`) or ``parts`` (the distance to the other objects' convex parts: these arrays).
GEOMETRY_DISTANCES = ("chamfer", "parts")
#: ``geometry_distance`` values whose model reads these arrays.
READS_PARTS = ("parts",)


def check_geometry_distance(value: str, key: str = "model.config.geometry_distance") -> str:
    """``value`` when it is one of :data:`GEOMETRY_DISTANCES`, else ``ValueError`` naming ``key`` and the value."""
    if str(value) not in GEOMETRY_DISTANCES:
        raise ValueError(f"{key}: unknown '{value}' (choose from {list(GEOMETRY_DISTANCES)})")
    return str(value)


def unique_planes(normals: np.ndarray, offsets: np.ndarray, decimals: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """The distinct face planes (n, d) of a convex part's triangles (coplanar faces merged)."""
    key = np.round(np.concatenate([normals, offsets[:, None]], axis=1), decimals)
    _, first = np.unique(key, axis=0, return_index=True)
    first = np.sort(first)
    return normals[first], offsets[first]


def spread_planes(normals: np.ndarray, count: int) -> np.ndarray:
    """Indices of ``count`` planes whose normals are spread (farthest-point order from the first)."""
    chosen = [0]
    gap = np.full(len(normals), np.inf)
    for _ in range(count - 1):
        gap = np.minimum(gap, 1.0 - normals @ normals[chosen[-1]])
        gap[chosen] = -np.inf
        chosen.append(int(np.argmax(gap)))
    return np.asarray(chosen)


def asset_part_planes(parts: Sequence, source: str = "asset") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(planes (PART_CAP, FACE_CAP, 4), boxes (PART_CAP, 2, 3), valid (PART_CAP,)) float32/bool of an asset's
    convex parts (trimesh meshes, canonical frame, metres); see the module docstring."""
    if not len(parts):
        raise ValueError(f"{source}: no convex parts to read part planes from")
    order = sorted(range(len(parts)), key=lambda k: -abs(float(parts[k].volume)))[:PART_CAP]
    planes = np.zeros((PART_CAP, FACE_CAP, 4), np.float32)
    boxes = np.zeros((PART_CAP, 2, 3), np.float32)
    valid = np.zeros(PART_CAP, bool)
    for slot, k in enumerate(sorted(order)):
        part = parts[k]
        tri = np.asarray(part.triangles, np.float64)
        normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        length = np.linalg.norm(normals, axis=1)
        keep = length > 1e-12
        if not keep.any():
            continue
        normals = normals[keep] / length[keep, None]
        offsets = (normals * tri[keep, 0]).sum(1)
        normals, offsets = unique_planes(normals, offsets)
        if len(normals) > FACE_CAP:
            pick = spread_planes(normals, FACE_CAP)
            # the kept planes moved out to touch the part: a polytope round it, as tight as these normals allow
            vertices = np.asarray(part.vertices, np.float64)
            normals, offsets = normals[pick], (vertices @ normals[pick].T).max(0)
        fill = np.arange(FACE_CAP)
        fill[len(normals):] = 0  # repeats of the first plane
        planes[slot, :, :3], planes[slot, :, 3] = normals[fill], offsets[fill]
        boxes[slot] = np.asarray(part.bounds, np.float32)
        valid[slot] = True
    if not valid.any():
        raise ValueError(f"{source}: its convex parts have no faces")
    return planes, boxes, valid


def mirror_planes(planes: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The part planes and boxes of an asset mirrored x → −x (:func:`spread.data.augment.mirror_local`)."""
    planes = np.array(planes, copy=True)
    planes[..., 0] = -planes[..., 0]
    mirrored = np.array(boxes, copy=True)
    mirrored[..., 0, 0], mirrored[..., 1, 0] = -boxes[..., 1, 0], -boxes[..., 0, 0]
    return planes, mirrored
