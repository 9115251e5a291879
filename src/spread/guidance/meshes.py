"""Per-asset guidance geometry and the padded per-batch tensors the guidance terms pose.

Each asset contributes (canonical frame: metres, y-up, centred at its bbox centre, DESIGN §3):

* its visual mesh's vertices (V, 3) and faces (F, 3), plus which faces are non-degenerate (boolean
  unions leave a few zero-area slivers, whose normal and circumcircle are undefined);
* the indices of its convex-hull vertices: an object resting on a plane touches it at hull vertices,
  and an object's AABB and xz hull are its hull vertices' (gravity, relation and the broad phase use
  them: far fewer points);
* a python-fcl ``BVHModel`` over all its triangles (OBBRSS, fcl's default), so a collision query
  reports triangle indices (:attr:`AssetMesh.bvh`). Built on the host path's first query of the asset
  (``guidance.detect: host``; the device path never imports fcl), kept for the process.

A batch (:class:`SceneMeshes`) holds them padded to (B, N, V_max / F_max / H_max): padded vertices
are 0 with a False mask, padded faces point at vertex 0 and are invalid, padded hull slots repeat the
first hull vertex (harmless for minima/maxima and hulls). Posing is one einsum:
``v_world = R · v_local + t`` (:meth:`SceneMeshes.pose`), differentiable in R and t.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

#: Triangles with less area than this (m²) are degenerate and never take part in a collision pair.
MIN_FACE_AREA = 1e-10


@dataclass(frozen=True)
class AssetMesh:
    """One asset's guidance geometry (module docstring), canonical frame, metres."""

    asset_id: str
    vertices: np.ndarray  # (V, 3) float64
    faces: np.ndarray  # (F, 3) int64
    valid_faces: np.ndarray  # (F,) bool, area ≥ MIN_FACE_AREA
    hull: np.ndarray  # (H,) int64, indices into vertices of the convex hull's vertices

    @functools.cached_property
    def bvh(self):
        """python-fcl's ``BVHModel`` of all its triangles, built on first use."""
        return _bvh(self.vertices, self.faces)


_MESHES: dict[tuple[str, str], AssetMesh] = {}


def _hull_indices(vertices: np.ndarray) -> np.ndarray:
    from scipy.spatial import ConvexHull
    from scipy.spatial import QhullError

    try:
        return np.sort(ConvexHull(vertices).vertices).astype(np.int64)
    except QhullError:  # flat or degenerate point set: every vertex is a candidate
        return np.arange(len(vertices), dtype=np.int64)


def _bvh(vertices: np.ndarray, faces: np.ndarray):
    import fcl

    model = fcl.BVHModel()
    model.beginModel(len(vertices), len(faces))
    model.addSubModel(np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int32))
    model.endModel()
    return model


def asset_mesh(library, asset_id: str) -> AssetMesh:
    """The :class:`AssetMesh` of ``asset_id`` (cached per content hash). Unknown ids raise the
    library's ``AssetError`` naming the id."""
    record = library[asset_id]
    key = (record.content_hash, asset_id)
    hit = _MESHES.get(key)
    if hit is None:
        mesh = library.mesh(asset_id)
        vertices = np.asarray(mesh.vertices, np.float64)
        faces = np.asarray(mesh.faces, np.int64)
        a, b, c = (vertices[faces[:, k]] for k in range(3))
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        hit = _MESHES[key] = AssetMesh(asset_id, vertices, faces, area >= MIN_FACE_AREA, _hull_indices(vertices))
    return hit


class SceneMeshes:
    """Padded canonical geometry of a batch of scenes.

    ``asset_ids[b]`` lists scene b's real objects in object order; they occupy the True slots of
    ``mask[b]`` (B, N) in order. Tensors (float64 canonical, cast on demand by :meth:`tensors`):

    ========== ================= ==================================================
    vertices   (B, N, V, 3)      canonical vertices, 0 at padding
    vmask      (B, N, V) bool    real vertices of real objects
    faces      (B, N, F, 3) long vertex indices within the object (0 at padding)
    fvalid     (B, N, F) bool    real, non-degenerate faces
    hull       (B, N, H) long    hull vertex indices (padded with the first one)
    hmask      (B, N, H) bool    real hull slots of real objects
    ========== ================= ==================================================
    """

    def __init__(self, library, asset_ids, mask: torch.Tensor):
        mask = mask.bool().cpu()
        B, N = mask.shape
        if len(asset_ids) != B:
            raise ValueError(f"guidance: asset_ids has {len(asset_ids)} scenes, mask has {B}")
        self.slots: list[np.ndarray] = []
        self.meshes: list[list[AssetMesh | None]] = []
        for b in range(B):
            slots = np.flatnonzero(mask[b].numpy())
            ids = list(asset_ids[b])
            if len(ids) != len(slots):
                raise ValueError(f"guidance: scene {b} has {len(ids)} asset ids but {len(slots)} real objects in mask")
            row: list[AssetMesh | None] = [None] * N
            for slot, aid in zip(slots, ids):
                row[slot] = asset_mesh(library, str(aid))
            self.slots.append(slots)
            self.meshes.append(row)
        present = [m for row in self.meshes for m in row if m is not None]
        V = max((len(m.vertices) for m in present), default=1)
        F = max((len(m.faces) for m in present), default=1)
        H = max((len(m.hull) for m in present), default=1)
        self.shape = (B, N, V, F, H)
        vertices = np.zeros((B, N, V, 3))
        vmask = np.zeros((B, N, V), bool)
        faces = np.zeros((B, N, F, 3), np.int64)
        fvalid = np.zeros((B, N, F), bool)
        hull = np.zeros((B, N, H), np.int64)
        hmask = np.zeros((B, N, H), bool)
        for b, row in enumerate(self.meshes):
            for i, m in enumerate(row):
                if m is None:
                    continue
                nv, nf, nh = len(m.vertices), len(m.faces), len(m.hull)
                vertices[b, i, :nv] = m.vertices
                vmask[b, i, :nv] = True
                faces[b, i, :nf] = m.faces
                fvalid[b, i, :nf] = m.valid_faces
                hull[b, i, :nh] = m.hull
                hull[b, i, nh:] = m.hull[0]
                hmask[b, i, :nh] = True
        self._cpu = {
            "vertices": torch.from_numpy(vertices), "vmask": torch.from_numpy(vmask),
            "faces": torch.from_numpy(faces), "fvalid": torch.from_numpy(fvalid),
            "hull": torch.from_numpy(hull), "hmask": torch.from_numpy(hmask),
        }
        self._cast: dict[tuple, dict[str, torch.Tensor]] = {}

    def tensors(self, device: torch.device, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        """The padded tensors on ``device``, vertices in ``dtype`` (cached per device and dtype)."""
        key = (str(device), dtype)
        out = self._cast.get(key)
        if out is None:
            out = {k: v.to(device=device, dtype=dtype if v.is_floating_point() else v.dtype)
                   for k, v in self._cpu.items()}
            self._cast[key] = out
        return out

    def pose(self, translation: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
        """World vertices (B, N, V, 3) = R · v + t for translation (B, N, 3) metres and rotation
        (B, N, 3, 3) world-from-local."""
        local = self.tensors(translation.device, translation.dtype)["vertices"]
        return torch.einsum("bnij,bnvj->bnvi", rotation, local) + translation[..., None, :]

    def hull_points(self, world: torch.Tensor) -> torch.Tensor:
        """The hull vertices (B, N, H, 3) of posed vertices ``world`` (B, N, V, 3)."""
        hull = self.tensors(world.device, world.dtype)["hull"]
        return torch.gather(world, 2, hull[..., None].expand(*hull.shape, 3))

    def triangles(self, world: torch.Tensor, b: torch.Tensor, i: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        """World triangles (P, 3, 3) [corner, xyz] of faces ``f`` of objects ``(b, i)`` (each (P,))."""
        faces = self.tensors(world.device, world.dtype)["faces"]
        corners = faces[b, i, f]  # (P, 3)
        return world[b[:, None], i[:, None], corners]
