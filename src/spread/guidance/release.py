"""The SPREAD release's own guidance terms: what ``guidance.mode=release`` steps with (the authors' refinement).

The release (reference notes §3) refines its sample with 100 iterations at t = 0 — a denoising projection, then
``x ← x − lr·(15·∇G_C′ + 2·∇G_R + [j ≥ 50]·2·∇G_H)`` with lr = 5e-4 — which is :meth:`SceneGuidance.refine`'s loop
with the paper's weights (7.5e-3, 1e-3, 1e-3), gravity from half-way, the upward collision boost and gravity's
y-only step. What differs from the platform's built-in terms is the terms themselves; here they are as the release
computes them, written from its description (the same quantities, not its code), in metres on the decoded poses:

* **collision** — the conical distance field on the BVH's triangle pairs (:mod:`spread.guidance.collision`), with
  the release's cone frames: unit normal n = w/(|w| + 1e-6) for w = (v1 − v0) × (v2 − v0); circumradius
  |e10||e20||e21|/(2|w| + 1e-6); circumcentre v2 + ((|e20|² e21 − |e21|² e20) × (e20 × e21))/(2(|w|² + 3·1e-6)),
  e_ab = v_a − v_b (so small triangles' centres are pulled towards v2, as the release's are); the quadratic part of
  φ as −(1 − 2h)/(4h² l² + 1e-6) − l/(2h) + (3 − 2h)/4 (zero at the release's h = 0.5); each corner's value
  Ψ² weighted by |n|² of the other triangle; a scene's G_C is the mean over its pairs' corners of both directions'
  values summed. Cones and supporters' corners detached as the platform's.
* **relation** — for each support pair (s supports o): the xz convex hull of s's vertices, its vertex indices
  chosen at the first evaluation and kept (the release caches them at its first refinement iteration; later
  evaluations take the same vertices at their new positions), detached; d(α) of each vertex α of o: 0 inside
  (every edge's cross product ≥ −1e-6), else the least distance to the hull's edges (projection parameter
  w·v/(v·v + 1e-8) clamped to [0, 1]); a pair counts when some d > 1e-6, costing Σ d / #(d > 1e-6); G_R is the mean
  over the counted pairs. Every object, welded or not (the release has no mounts).
* **gravity** — for each object: its posed vertices' axis-aligned box, centre c and lowest point y_min; a ray from
  c straight down hits the other objects' triangles (Möller–Trumbore, two-sided; a triangle with |det| < 1e-6 is
  parallel; u, v ≥ −1e-6, u + v ≤ 1 + 1e-6, t > 1e-6; the hit triangles detached, the ray's origin not), t the
  nearest hit or, with none, c_y (the floor y = 0); r = t − (c_y − y_min) − ε and G_H = Σ |r| over the objects
  with r > θ_H or r < 0 (ε = ``gap``, θ_H = ``tolerance``). Every object (no supporters or mounts are consulted:
  an object whose supporter is not under its centre is pulled to the floor, as in the release).

Not reproduced (the release's code has them, the platform's detection does not): its BVH also reports degenerate
(zero-area) faces, which add zero to a scene's sum but count in its mean; and it stops at 64 pairs per triangle.
"""

from __future__ import annotations

import numpy as np
import torch

from spread.guidance.collision import LINEAR_MAX, _up_boost
from spread.guidance.gravity import _y_only
from spread.guidance.terms import GuidanceTerm

#: The release's small constants (its loss.py and sampler): normals, circumcircles and cone radii (eps), hull tests.
EPS = 1e-6
HULL_INSIDE = -1e-6
EDGE_EPS = 1e-8
OUTSIDE = 1e-6
RAY_EPS = 1e-6


def cone_frames(triangles: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The release's cone of each triangle (P, 3, 3): unit normal (P, 3), circumcentre (P, 3), circumradius (P,),
    and the normal's length |n| (P,) (just under 1: the release's normalisation adds 1e-6)."""
    v0, v1, v2 = triangles.unbind(1)
    w = torch.linalg.cross(v1 - v0, v2 - v0, dim=-1)
    wn = w.norm(dim=-1, keepdim=True)
    e20, e21 = v0 - v2, v1 - v2
    e10 = e20 - e21
    radius = e10.norm(dim=-1) * e20.norm(dim=-1) * e21.norm(dim=-1) / (2.0 * wn[:, 0] + EPS)
    num = torch.linalg.cross((e20 ** 2).sum(-1, keepdim=True) * e21 - (e21 ** 2).sum(-1, keepdim=True) * e20,
                             torch.linalg.cross(e20, e21, dim=-1), dim=-1)
    centre = num / (2.0 * (w ** 2 + EPS).sum(-1, keepdim=True)) + v2
    normal = w / (wn + EPS)
    return normal, centre, radius, normal.norm(dim=-1)


def conical_field(points: torch.Tensor, normal: torch.Tensor, centre: torch.Tensor, radius: torch.Tensor,
                  height: float) -> torch.Tensor:
    """Ψ (P, K) of the release's cones at points (P, K, 3), metres (module docstring)."""
    d = points - centre[:, None, :]
    l = (d * normal[:, None, :]).sum(-1)
    rho = (d - l[..., None] * normal[:, None, :]).norm(dim=-1) / (radius[:, None] * (1 - l / height) + EPS)
    h = height
    quad = -(1.0 - 2.0 * h) / ((4.0 * h * h) * l * l + EPS) - l / (2.0 * h) + 0.25 * (3 - 2 * h)
    phi = torch.where((l <= -h) & (l > -LINEAR_MAX), -l + 1 - h, torch.where((l > -h) & (l < h), quad, 0.0 * l))
    return torch.where(rho < 1, ((1 - rho) * phi) ** 2, 0.0 * rho)


def collision_loss(world: torch.Tensor, meshes, pairs, supports: torch.Tensor, cone_height: float) -> torch.Tensor:
    """The release's G_C per scene (B,) for world vertices (B, N, V, 3) and the BVH's ``pairs`` (i < j: i's faces
    receive, as the release's lower face ids do); ``supports`` (B, N, N) bool, [b, i, j] = i supports j."""
    B = world.shape[0]
    out = world.new_zeros(B)
    if not len(pairs):
        return out + 0 * world.sum()
    device = world.device
    b, i, fi, j, fj = (t.to(device) for t in (pairs.b, pairs.i, pairs.fi, pairs.j, pairs.fj))
    tri_i, tri_j = meshes.triangles(world, b, i, fi), meshes.triangles(world, b, j, fj)
    query_i = torch.where(supports[b, i, j][:, None, None], tri_i.detach(), tri_i)
    query_j = torch.where(supports[b, j, i][:, None, None], tri_j.detach(), tri_j)
    n_i, c_i, r_i, len_i = cone_frames(tri_i.detach())
    n_j, c_j, r_j, len_j = cone_frames(tri_j.detach())
    at_j = conical_field(query_j, n_i, c_i, r_i, cone_height) ** 2 * (len_j ** 2)[:, None]  # i's cones, j's corners
    at_i = conical_field(query_i, n_j, c_j, r_j, cone_height) ** 2 * (len_i ** 2)[:, None]
    count = torch.zeros(B, device=device, dtype=world.dtype).index_add_(0, b, torch.ones_like(b, dtype=world.dtype))
    total = out.index_add(0, b, at_j.mean(1)) + out.index_add(0, b, at_i.mean(1))
    return total / count.clamp_min(1)


def hull_indices(guidance, b: int, i: int, world: torch.Tensor, vmask: torch.Tensor) -> torch.Tensor | None:
    """Indices of object (b, i)'s vertices on its xz convex hull (counter-clockwise), chosen at the first call and
    kept in ``guidance.cache`` (the release's first-iteration hull); None when the hull is degenerate."""
    key = ("release_hull", b, i)
    if key not in guidance.cache:
        from scipy.spatial import ConvexHull, QhullError

        real = torch.nonzero(vmask[b, i]).flatten()
        xz = world[b, i, real][:, [0, 2]].detach().cpu().numpy()
        try:
            guidance.cache[key] = real[torch.from_numpy(ConvexHull(xz).vertices).to(real.device)]
        except (QhullError, ValueError):
            guidance.cache[key] = None
    return guidance.cache[key]


def hull_distance(points: torch.Tensor, hull: torch.Tensor) -> torch.Tensor:
    """The release's distance (P,) of points (P, 2) to a CCW polygon (K, 2): 0 inside, else to the nearest edge."""
    v = torch.roll(hull, -1, 0) - hull
    w = points[:, None, :] - hull[None]
    inside = (v[:, 0] * w[..., 1] - v[:, 1] * w[..., 0] >= HULL_INSIDE).all(1)
    t = ((w * v).sum(-1) / ((v * v).sum(-1) + EDGE_EPS)).clamp(0, 1)
    dist = (points[:, None, :] - (hull[None] + t[..., None] * v)).norm(dim=-1).amin(1)
    return torch.where(inside, 0.0 * dist, dist)


def relation_loss(ctx) -> torch.Tensor:
    """The release's G_R per scene (B,) (module docstring)."""
    world = ctx.world
    B = world.shape[0]
    vmask = ctx.meshes.tensors(world.device, world.dtype)["vmask"]
    per_scene = [[] for _ in range(B)]
    for b, i, j in ctx.supports.nonzero().tolist():
        idx = hull_indices(ctx.guidance, b, i, world, vmask)
        if idx is None or len(idx) < 3:
            continue
        d = hull_distance(world[b, j, vmask[b, j]][:, [0, 2]], world[b, i, idx][:, [0, 2]].detach())
        outside = (d > OUTSIDE).sum()
        if outside > 0:
            per_scene[b].append(d.sum() / outside)
    zero = 0 * world.sum()
    return torch.stack([torch.stack(p).mean() if p else zero for p in per_scene])


def ray_down(origins: torch.Tensor, triangles: torch.Tensor, owner: torch.Tensor) -> torch.Tensor:
    """Nearest hit distance (N,) of rays from origins (N, 3) straight down against triangles (T, 3, 3) of other
    objects (``owner`` (T,): the object index of each); c_y where nothing is hit. The release's Möller–Trumbore with
    its tolerances; differentiable in the origins."""
    d = origins.new_tensor([0.0, -1.0, 0.0])
    v0 = triangles[None, :, 0]  # (1, T, 3)
    e1, e2 = triangles[None, :, 1] - v0, triangles[None, :, 2] - v0
    p = torch.linalg.cross(d.expand_as(e2), e2, dim=-1)
    det = (e1 * p).sum(-1)
    parallel = det.abs() < RAY_EPS
    inv = torch.where(parallel, 0.0 * det, 1.0 / torch.where(parallel, torch.ones_like(det), det))
    s = origins[:, None, :] - v0  # (N, T, 3)
    u = (s * p).sum(-1) * inv
    q = torch.linalg.cross(s, e1.expand_as(s), dim=-1)
    v = (q * d).sum(-1) * inv
    t = (e2 * q).sum(-1) * inv
    other = owner[None, :] != torch.arange(len(origins), device=origins.device)[:, None]
    hit = other & ~parallel & (u >= -RAY_EPS) & (v >= -RAY_EPS) & (u + v <= 1 + RAY_EPS) & (t > RAY_EPS)
    nearest = torch.where(hit, t, torch.full_like(t, torch.inf)).amin(-1)
    return torch.where(torch.isinf(nearest), origins[:, 1], nearest)


def gravity_loss(ctx) -> torch.Tensor:
    """The release's G_H per scene (B,) (module docstring); one scene at a time, over its real objects' faces."""
    world = ctx.world
    t = ctx.meshes.tensors(world.device, world.dtype)
    out = []
    for b in range(world.shape[0]):
        real = torch.nonzero(ctx.mask[b]).flatten()
        w, vmask = world[b, real], t["vmask"][b, real][..., None]  # (n, V, 3), (n, V, 1)
        lo = torch.where(vmask, w, torch.full_like(w, torch.inf)).amin(1)
        hi = torch.where(vmask, w, torch.full_like(w, -torch.inf)).amax(1)
        centre = (hi + lo) / 2.0
        height = centre[:, 1] - lo[:, 1]
        k, f = torch.nonzero(t["fvalid"][b, real], as_tuple=True)  # each real object's faces
        corners = t["faces"][b, real][k, f]  # (T, 3)
        triangles = w[k[:, None], corners].detach()  # (T, 3, 3)
        r = ray_down(centre, triangles, k) - height - ctx.config.gap
        bad = (r > ctx.config.tolerance) | (r < 0)
        out.append(torch.where(bad, r.abs(), 0.0 * r).sum())
    return torch.stack(out)


#: The release's three terms, under the built-ins' names, weights, schedules and gradient edits.
RELEASE_TERMS = {
    "collision": GuidanceTerm(
        "collision", lambda ctx: collision_loss(ctx.world, ctx.meshes, ctx.pairs(), ctx.supports, ctx.config.cone_height),
        weight=lambda config: config.collision, edit=_up_boost,
        description="the release's G_C: its cone frames on the BVH's triangle pairs"),
    "relation": GuidanceTerm(
        "relation", relation_loss, weight=lambda config: config.relation,
        description="the release's G_R: outside distance to the supporter's first-iteration xz hull"),
    "gravity": GuidanceTerm(
        "gravity", gravity_loss, weight=lambda config: config.gravity, start=lambda config: config.gravity_from,
        edit=_y_only, description="the release's G_H: one ray down from the box centre to any other object"),
}
