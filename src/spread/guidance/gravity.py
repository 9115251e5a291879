"""Gravity guidance G_H: the vertical gap from each object down to what it rests on, measured on meshes.

What an object rests on comes from the physical graph: its supporters (``physical[i, j] == 1``, i
supports j) or, when it has none, the floor y = 0 (DESIGN §3). The gap d_j (metres):

* floor: the lowest point of j, ``min y`` over its (hull) vertices;
* supporter(s): a vertical ray down through each hull vertex v of j, starting at the height of j's
  AABB centre (as the release's ray does, so a slightly sunk object still sees the surface it sank
  into, and a shelf board above it is ignored), hits the supporters' upward-facing triangles; h(v)
  is the highest hit, and ``d_j = min_v (v_y − h(v))`` over the vertices with a hit. Unlike the
  release's single ray from the centre, an object whose supporter is not under its centre is still
  held at its supporter's height (an overhanging cup, a plate on a narrow stand). When no vertex is
  over a supporter, the gap is to the top of the supporters' AABBs (relation guidance pulls it over).

Hull vertices suffice: a rigid object resting on a surface touches it at vertices of its convex hull.
The hit heights are detached (what lies under an object is not moved by gravity on it), so the
gradient reaches only j's pose: ``∂d_j = ∂v*_y`` of the vertex attaining the minimum.

Then r_j = d_j − ε and ``G_H = Σ_j |r_j| [r_j > θ_H or r_j < 0]`` over a scene's objects (paper eq.
G_H; release ε = 5e-4 m, θ_H = 2e-3 m): floating and sinking are penalised, a gap in [ε, ε + θ_H] is not.

``settle`` (G_S, not the paper's; ``guidance.terms.settle=λ``) measures the same gaps (its rays start at least
``guidance.settle_reach`` above the object's lowest point: 0.15 m), leaves out a supported object that is beside its
supporters rather than over them, and is quadratic, scaled so that a step of weight λ closes the fraction λ of each
gap (:func:`settle_loss`); same schedule (``gravity_from``) and y-only step. The states' y must be normalised through
``bounds`` (SPREAD's, and the baselines' decode, which map [−1, 1] to the same bounds).
"""

from __future__ import annotations

import torch

from spread.guidance.terms import GuidanceTerm, register_term

#: Barycentric slack for a vertical ray through a triangle's edge (dimensionless).
BARY_TOLERANCE = 1e-9


def _cross2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """2D cross product of (..., 2) vectors in the (x, z) plane."""
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def ray_heights(points: torch.Tensor, start: torch.Tensor, triangles: torch.Tensor,
                valid: torch.Tensor) -> torch.Tensor:
    """Highest hit (S, H) of downward vertical rays through points (S, H, 3) starting at heights start
    (S,) with triangles (S, F, 3, 3) [corner, xyz] (valid (S, F) bool; only upward-facing ones count);
    −inf where a ray hits nothing. Not differentiable (call under no_grad).

    Only the (pair, triangle) candidates that face up and whose xz box meets the points' xz box are
    tested (typically a few per pair: a table top's triangles under a cup), then scattered back."""
    S, H = points.shape[:2]
    out = torch.full((S, H), -torch.inf, dtype=points.dtype, device=points.device)
    a, b, c = triangles.unbind(2)  # (S, F, 3)
    xz = [0, 2]
    e1, e2 = (b - a)[..., xz], (c - a)[..., xz]
    den = _cross2(e1, e2)  # = −n_y of the normal (b − a) × (c − a): < 0 for an upward-facing triangle
    tri_lo, tri_hi = triangles[..., xz].amin(2), triangles[..., xz].amax(2)  # (S, F, 2)
    pts_lo, pts_hi = points[..., xz].amin(1), points[..., xz].amax(1)  # (S, 2)
    near = ((tri_lo <= pts_hi[:, None]) & (tri_hi >= pts_lo[:, None])).all(-1)
    near &= valid & (den < -1e-12) & (triangles[..., 1].amin(-1) <= start[:, None])
    s, f = near.nonzero(as_tuple=True)  # candidates (C,)
    if not len(s):
        return out
    a0, e1, e2, den = a[s, f], e1[s, f], e2[s, f], den[s, f]  # (C, 3), (C, 2), (C, 2), (C,)
    q = points[s][..., xz] - a0[:, None, xz]  # (C, H, 2)
    u = _cross2(q, e2[:, None]) / den[:, None]
    v = _cross2(e1[:, None], q) / den[:, None]
    y = a0[:, None, 1] + u * (b[s, f, 1] - a0[:, 1])[:, None] + v * (c[s, f, 1] - a0[:, 1])[:, None]
    hit = (u >= -BARY_TOLERANCE) & (v >= -BARY_TOLERANCE) & (u + v <= 1 + BARY_TOLERANCE) & (y <= start[s, None])
    y = torch.where(hit, y, torch.full_like(y, -torch.inf))
    return out.scatter_reduce(0, s[:, None].expand(-1, H), y, "amax")


def vertical_gaps(world: torch.Tensor, hull: torch.Tensor, meshes, supports: torch.Tensor,
                  beside: str = "roof", reach: float = 0.0, pairs: torch.Tensor | None = None) -> torch.Tensor:
    """Gap d (B, N) metres from each object to what it rests on (module docstring); ``world`` (B, N, V, 3)
    posed vertices, ``hull`` (B, N, H, 3) their hull vertices, ``supports`` (B, N, N) bool. ``beside``: the gap of
    a supported object none of whose vertices is over a supporter — ``roof``: to the top of the supporters' AABBs
    (G_H), ``nan``: none (NaN; the settle term leaves such an object to relation guidance). ``reach`` (metres): the
    rays start at least this far above the object's lowest point (0: at its AABB centre, G_H), so that a thin
    object sunk deeper than half its height still sees the surface it sank into. ``pairs``: ``supports.nonzero()``
    when the caller has it already (the guidance finds it once per sample: no host read per step)."""
    if beside not in ("roof", "nan"):
        raise ValueError(f"vertical_gaps: beside must be 'roof' or 'nan', got {beside!r}")
    B, N, H, _ = hull.shape
    t = meshes.tensors(world.device, world.dtype)
    hmask = t["hmask"]
    y = hull[..., 1]
    lowest = torch.where(hmask, y, torch.full_like(y, torch.inf)).amin(-1)  # (B, N); inf at padding
    pairs = supports.nonzero() if pairs is None else pairs
    if not len(pairs):
        return lowest
    b, i, j = pairs.unbind(1)
    with torch.no_grad():
        top = torch.where(hmask, y, torch.full_like(y, -torch.inf)).amax(-1)  # (B, N)
        start = torch.maximum(0.5 * (lowest + top), lowest + reach)
        faces = t["faces"][b, i]  # (S, F, 3)
        S = len(pairs)
        triangles = world[b, i][torch.arange(S, device=world.device)[:, None, None], faces]  # (S, F, 3, 3)
        heights = ray_heights(hull[b, j].detach(), start[b, j], triangles, t["fvalid"][b, i])
        slot = b * N + j
        h = torch.full((B * N, H), -torch.inf, device=world.device, dtype=world.dtype)
        h = h.scatter_reduce(0, slot[:, None].expand(-1, H), heights, "amax")
        roof = torch.full((B * N,), -torch.inf, device=world.device, dtype=world.dtype)
        roof = roof.scatter_reduce(0, slot, top[b, i], "amax")
        h, roof = h.view(B, N, H), roof.view(B, N)
        hit = torch.isfinite(h) & hmask
    over = torch.where(hit, y - torch.where(hit, h, torch.zeros_like(h)), torch.full_like(y, torch.inf)).amin(-1)
    supported = supports.any(1)
    to_support = torch.where(hit.any(-1), over, lowest - roof if beside == "roof" else torch.full_like(over, torch.nan))
    return torch.where(supported, to_support, lowest)


def gravity_loss(gaps: torch.Tensor, mask: torch.Tensor, gap: float, tolerance: float) -> torch.Tensor:
    """G_H per scene (B,): Σ |r| over real objects with r = d − ε outside [0, θ_H] (metres)."""
    r = torch.where(mask, gaps - gap, torch.zeros_like(gaps))
    bad = mask & ((r > tolerance) | (r < 0))
    return torch.where(bad, r.abs(), torch.zeros_like(r)).sum(-1)


def settle_loss(gaps: torch.Tensor, mask: torch.Tensor, bounds: torch.Tensor, gap: float,
                tolerance: float) -> torch.Tensor:
    """G_S per scene (B,): ``½ Σ (r / s_y)²`` over real objects with a gap (not NaN) and r = d − ε outside
    [0, θ_H]; s_y = (y_max − y_min) / 2 of ``bounds`` (6,), the metres per unit of the normalised y channel.

    Its gradient on the normalised y of an object is r / s_y, so a step of weight λ moves the object by λ·r
    metres: λ is the fraction of its gap (floating or sinking) an object closes per step — whatever the room's
    height range and the gap's size. G_H (Σ |r|) moves every object by the same λ·s_y² per step instead: too
    little for an object 30 cm above a bed in the iterations it has, and past its target for a small gap."""
    scale = 0.5 * (bounds[4] - bounds[1])
    r = gaps - gap
    bad = mask & torch.isfinite(r) & ((r > tolerance) | (r < 0))
    r = torch.where(bad, r / scale, torch.zeros_like(r))
    return 0.5 * (r * r).sum(-1)


def _y_only(grad: torch.Tensor, config) -> torch.Tensor:
    """The release keeps the gravity step on the normalised-y channel only (``gravity_y_only``)."""
    if not config.gravity_y_only:
        return grad
    only_y = torch.zeros_like(grad)
    only_y[..., 1] = grad[..., 1]
    return only_y


register_term(GuidanceTerm(
    "gravity", lambda ctx: gravity_loss(vertical_gaps(ctx.world, ctx.hull, ctx.meshes, ctx.supports,
                                                      pairs=ctx.support_pairs), ctx.falls,
                                        ctx.config.gap, ctx.config.tolerance),
    start=lambda config: config.gravity_from, edit=_y_only,
    description="G_H: vertical gap to the supporter or the floor outside [ε, ε + θ_H]"))
register_term(GuidanceTerm(
    "settle", lambda ctx: settle_loss(vertical_gaps(ctx.world, ctx.hull, ctx.meshes, ctx.supports, beside="nan",
                                                    reach=ctx.config.settle_reach,
                                                    pairs=ctx.support_pairs),
                                      ctx.falls, ctx.bounds, ctx.config.gap, ctx.config.tolerance),
    start=lambda config: config.gravity_from, edit=_y_only,
    description="G_S: the gravity gap closed by the fraction λ per step (objects over a supporter or on the floor)"))
