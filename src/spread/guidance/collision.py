"""Collision guidance G_C: BVH triangle-pair detection, then the conical distance field (CoDF).

Detection (not differentiable, CPU, float64): a broad phase over the objects' world AABBs (from their
posed hull vertices) keeps the object pairs of a scene whose boxes overlap; python-fcl then collides
the two objects' triangle BVHs (:mod:`spread.guidance.meshes`), which reports every intersecting
triangle pair (b1 indexes the first object's faces, b2 the second's) up to ``max_contacts`` per
object pair. ``enable_contact`` is left off: it reports the same triangle pairs (only duplicated,
one entry per contact point) at ~1.5× the cost. Like the release's BVH, only intersecting surfaces
are found: a mesh wholly inside another is not (the geometry model and the evaluation see it).

Penalty (Tzionas et al. 2016, as the release's ``DistanceFieldPenetrationLoss``): each triangle
carries a cone on its outward normal n, apex at height h above its circumcentre c, base radius its
circumradius R_c; at a point p, with l = (p − c)·n and ρ = |(p − c) − l n| / (R_c (1 − l/h)),

    Ψ(p) = [ρ < 1] · ((1 − ρ) · φ(l))²,   φ(l) = −l + 1 − h  (l ≤ −h),
                                          φ(l) = −(1 − 2h)/(4h²) l² − l/(2h) + (3 − 2h)/4  (−h < l < h),
                                          φ(l) = 0  (l ≥ h)

(at h = 0.5, the release's value, φ = 0.5 − l below the apex). A colliding pair (t_a, t_b) costs the
mean of Ψ² of t_a's cone at t_b's three corners plus the same the other way round; a scene's G_C is
the mean over its pairs (paper eq. G_C), so batching never changes a scene's gradient. The cones are
detached (the release's choice: a triangle is pushed by the field it is in, not by moving its own
field), and an object's corners are detached where it supports the other object of the pair, so a
supporter is never pushed by what it supports. Gradients reach translation and rot6d through the
query corners.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from spread.guidance.terms import GuidanceTerm, register_term

#: Points below the receiving triangle deeper than this (metres) get no penalty (release: linear_max).
LINEAR_MAX = 1000.0


@dataclass
class TrianglePairs:
    """Colliding triangle pairs of a batch, each (P,) long: scene b, objects i ≠ j, faces fi of i, fj of j."""

    b: torch.Tensor
    i: torch.Tensor
    fi: torch.Tensor
    j: torch.Tensor
    fj: torch.Tensor
    object_pairs: int = 0  # object pairs given to fcl

    def __len__(self) -> int:
        return int(self.b.numel())

    @classmethod
    def empty(cls, object_pairs: int = 0) -> "TrianglePairs":
        z = torch.zeros(0, dtype=torch.long)
        return cls(z, z, z, z, z, object_pairs)


def overlapping_pairs(lo: torch.Tensor, hi: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(K, 3) [b, i, j], i < j, of real objects whose world AABBs lo/hi (B, N, 3) overlap (``mask`` (B, N)): the broad
    phase of both detection paths (``guidance.detect``), on the tensors' device."""
    N = lo.shape[1]
    overlap = ((lo[:, :, None, :] <= hi[:, None, :, :]) & (hi[:, :, None, :] >= lo[:, None, :, :])).all(-1)
    overlap &= mask[:, :, None] & mask[:, None, :]
    overlap &= torch.ones(N, N, dtype=torch.bool, device=lo.device).triu(1)
    return overlap.nonzero()


class TriangleCollider:
    """fcl collision objects of a batch (one per real object, sharing the assets' BVHs); :meth:`find`
    poses them and returns the colliding triangle pairs between different objects."""

    def __init__(self, meshes, max_contacts: int):
        import fcl

        self.meshes = meshes
        self.request = fcl.CollisionRequest(num_max_contacts=int(max_contacts), enable_contact=False)
        self.objects = [[None if m is None else fcl.CollisionObject(m.bvh, fcl.Transform()) for m in row]
                        for row in meshes.meshes]
        self.valid = self.meshes.tensors(torch.device("cpu"), torch.float64)["fvalid"].numpy()  # (B, N, F)

    def find(self, rotation: np.ndarray, translation: np.ndarray, lo: np.ndarray, hi: np.ndarray,
             mask: np.ndarray) -> TrianglePairs:
        """Pairs for poses rotation (B, N, 3, 3), translation (B, N, 3) (float64 numpy, metres) and the
        objects' world AABBs lo/hi (B, N, 3)."""
        import fcl

        candidates = overlapping_pairs(torch.from_numpy(lo), torch.from_numpy(hi), torch.from_numpy(mask)).numpy()
        if not len(candidates):
            return TrianglePairs.empty()
        posed: set[tuple[int, int]] = set()
        chunks = []
        for b, i, j in candidates:
            for k in (i, j):
                if (b, k) not in posed:
                    self.objects[b][k].setTransform(fcl.Transform(rotation[b, k], translation[b, k]))
                    posed.add((b, k))
            result = fcl.CollisionResult()
            if not fcl.collide(self.objects[b][i], self.objects[b][j], self.request, result):
                continue
            faces = np.array([(c.b1, c.b2) for c in result.contacts], np.int64)
            faces = np.unique(faces, axis=0)
            faces = faces[self.valid[b, i, faces[:, 0]] & self.valid[b, j, faces[:, 1]]]
            if len(faces):
                chunks.append(np.column_stack([np.full(len(faces), b), np.full(len(faces), i), faces[:, 0],
                                               np.full(len(faces), j), faces[:, 1]]))
        if not chunks:
            return TrianglePairs.empty(len(candidates))
        rows = torch.from_numpy(np.concatenate(chunks))
        return TrianglePairs(*rows.unbind(1), object_pairs=len(candidates))


def cone_frames(triangles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Unit normal n (P, 3), circumcentre c (P, 3), circumradius R_c (P,) of triangles (P, 3, 3)."""
    a, b, c = triangles.unbind(1)
    u, v = b - a, c - a
    w = torch.linalg.cross(u, v, dim=-1)
    w2 = (w * w).sum(-1, keepdim=True)
    normal = w / w2.sqrt()
    centre = a + ((u * u).sum(-1, keepdim=True) * torch.linalg.cross(v, w, dim=-1)
                  + (v * v).sum(-1, keepdim=True) * torch.linalg.cross(w, u, dim=-1)) / (2 * w2)
    return normal, centre, (centre - a).norm(dim=-1)


def conical_field(points: torch.Tensor, normal: torch.Tensor, centre: torch.Tensor, radius: torch.Tensor,
                  height: float) -> torch.Tensor:
    """Ψ (P, K) of each pair's cone (normal, centre (P, 3), radius (P,)) at its points (P, K, 3), metres."""
    d = points - centre[:, None, :]
    l = (d * normal[:, None, :]).sum(-1)
    radial = d - l[..., None] * normal[:, None, :]
    dist = (radial * radial).sum(-1).clamp_min(1e-24).sqrt()
    rho = dist / (radius[:, None] * (1 - l / height) + 1e-6)
    h = height
    inner = -(1 - 2 * h) / (4 * h * h) * l * l - l / (2 * h) + (3 - 2 * h) / 4
    phi = torch.where(l <= -h, -l + 1 - h, inner)
    phi = torch.where((l >= h) | (l <= -LINEAR_MAX), torch.zeros_like(phi), phi)
    inside = (rho < 1) & (l < h)
    return torch.where(inside, ((1 - rho) * phi) ** 2, torch.zeros_like(phi))


def collision_loss(world: torch.Tensor, meshes, pairs: TrianglePairs, supports: torch.Tensor, cone_height: float,
                   detach_cones: bool = True) -> torch.Tensor:
    """G_C per scene (B,) for world vertices (B, N, V, 3) and the detected ``pairs``; ``supports``
    (B, N, N) bool, [b, i, j] = i supports j. 0 for scenes without colliding pairs."""
    B = world.shape[0]
    out = world.new_zeros(B)
    if not len(pairs):
        return out + 0 * world.sum()  # keeps the graph (a zero gradient) when nothing collides
    device = world.device
    b, i, fi, j, fj = (t.to(device) for t in (pairs.b, pairs.i, pairs.fi, pairs.j, pairs.fj))
    tri_i = meshes.triangles(world, b, i, fi)
    tri_j = meshes.triangles(world, b, j, fj)
    # an object's corners are fixed where it supports the other object
    pin_i = supports[b, i, j][:, None, None]
    pin_j = supports[b, j, i][:, None, None]
    query_i = torch.where(pin_i, tri_i.detach(), tri_i)
    query_j = torch.where(pin_j, tri_j.detach(), tri_j)
    cone_i = cone_frames(tri_i.detach() if detach_cones else query_i)
    cone_j = cone_frames(tri_j.detach() if detach_cones else query_j)
    psi_at_j = conical_field(query_j, *cone_i, cone_height)  # i's cones at j's corners
    psi_at_i = conical_field(query_i, *cone_j, cone_height)
    per_pair = (psi_at_j ** 2).mean(1) + (psi_at_i ** 2).mean(1)
    count = torch.zeros(B, device=device, dtype=world.dtype).index_add_(0, b, torch.ones_like(per_pair))
    total = out.index_add(0, b, per_pair)
    return total / count.clamp_min(1)


def _up_boost(grad: torch.Tensor, config) -> torch.Tensor:
    """The release's tweak: the upward part of the collision step on the normalised-y channel × ``up_boost``."""
    if config.up_boost == 1.0:
        return grad
    y = grad[..., 1]
    grad = grad.clone()
    grad[..., 1] = torch.where(y < 0, y * config.up_boost, y)
    return grad


register_term(GuidanceTerm(
    "collision", lambda ctx: collision_loss(ctx.world, ctx.meshes, ctx.pairs(), ctx.supports, ctx.config.cone_height,
                                            ctx.detach_cones),
    edit=_up_boost,
    description="G_C: conical distance field on the BVH's triangle pairs between different objects"))
