"""Relation (support) guidance G_R: keep a supported object's footprint over its supporter's.

For each support pair (i supports j, ``physical[i, j] == 1``) the supporter's footprint is the convex
hull of its posed vertices projected on the floor plane (x, z) — computed each call from its posed
hull vertices (scipy on the host, or :func:`spread.guidance.dense.hull_edges` on the states' device with
``guidance.detect: device``), detached, as the release detaches it. Each vertex α of j (all mesh
vertices, projected on (x, z)) outside that polygon is at distance s(α, i) from it (metres);
V_ij is the set of such vertices (s > 1e-6). Paper eq. G_R, per scene:

    G_R = Σ_{(i,j) ∈ E} Σ_{α ∈ V_ij} s(α, i) / (|V_ij| · |E|)

with E the scene's support pairs (the release divides by the pairs with some vertex outside
instead; the paper's |E| is used here). The gradient reaches j's translation (x, z) and rotation.

``over`` (G_O, not the paper's; ``guidance.terms.over=λ``) measures the same outside vertices in the normalised
state's units and is quadratic per pair, not averaged over the pairs, so that a step of weight λ closes about the
fraction λ of each pair's mean outside distance (:func:`over_loss`). ``home`` (not the paper's;
``guidance.terms.home=λ``) is linear in the same distance, plus a lift while j is wholly beside and below its
supporter's top, so that a step moves j by λ normalised units whatever the distance (:func:`home_loss`): the
objects a network samples a metre off what holds them arrive in the iterations there are.
"""

from __future__ import annotations

import numpy as np
import torch

from spread.guidance.dense import hull_edges
from spread.guidance.terms import GuidanceTerm, register_term

#: A vertex counts as outside when it is farther than this from the hull (metres; release 1e-6).
OUTSIDE = 1e-6


def footprint(points_xz: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex polygon (K, 2) in (x, z) of points (P, 2); their bounding rectangle when
    they are collinear (a degenerate hull)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return points_xz[ConvexHull(points_xz).vertices]
    except (QhullError, ValueError):
        lo, hi = points_xz.min(0), points_xz.max(0)
        return np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]]])


def polygon_distance(points: torch.Tensor, polygons: torch.Tensor) -> torch.Tensor:
    """Distance (S, P) of points (S, P, 2) outside convex CCW polygons (S, K, 2) (0 inside, metres).

    Polygons may be padded by repeating a vertex (a zero-length edge changes nothing)."""
    return segments_distance(points, polygons, torch.roll(polygons, -1, dims=1))


def segments_distance(points: torch.Tensor, start: torch.Tensor, end: torch.Tensor,
                      valid: torch.Tensor | None = None) -> torch.Tensor:
    """Distance (S, P) of points (S, P, 2) outside the convex region left of every edge start → end (S, K, 2) of
    its row (0 inside: left of all of them within 1e-9), measured to the nearest edge; ``valid`` (S, K) leaves
    edges out (the device path's hull edges, :func:`spread.guidance.dense.hull_edges`)."""
    q = start[:, None, :, :]  # (S, 1, K, 2)
    e = end[:, None] - q
    d = points[:, :, None, :] - q  # (S, P, K, 2)
    cross = e[..., 0] * d[..., 1] - e[..., 1] * d[..., 0]
    t = ((d * e).sum(-1) / (e * e).sum(-1).clamp_min(1e-18)).clamp(0, 1)
    off = d - t[..., None] * e
    dist = (off * off).sum(-1).clamp_min(1e-24)
    if valid is not None:
        cross = torch.where(valid[:, None, :], cross, torch.full_like(cross, torch.inf))
        dist = torch.where(valid[:, None, :], dist, torch.full_like(dist, torch.inf))
    inside = (cross >= -1e-9).all(-1)
    dist = dist.amin(-1).sqrt()
    return torch.where(inside, torch.zeros_like(dist), dist)


def outside_distances(world: torch.Tensor, hull: torch.Tensor, meshes, supports: torch.Tensor,
                      pairs: torch.Tensor | None = None, device: bool = False, share: bool = False
                      ) -> tuple[torch.Tensor, ...] | None:
    """Per support pair (``supports`` (B, N, N) bool, [b, i, j]: i supports j): its scene b (S,) and the mean
    distance (S,) of j's vertices outside i's footprint, ``Σ_{α ∈ V_ij} s(α, i) / |V_ij|`` (0 when none is), in the
    units of ``world`` (B, N, V, 3) and ``hull`` (B, N, H, 3); None when the batch has no support pair. ``pairs``:
    ``supports.nonzero()`` when the caller has it already (found once per sample). ``device``: the footprints' hull
    edges found by tensor operations where ``world`` is (``guidance.detect: device``), not by scipy on the host.
    ``share``: also the share (S,) of j's vertices outside (1: j wholly beside its supporter)."""
    pairs = supports.nonzero() if pairs is None else pairs
    if not len(pairs):
        return None
    b, i, j = pairs.unbind(1)
    t = meshes.tensors(world.device, world.dtype)
    if device:
        # each pair's supporter's hull edges, found on the states' device (dense.hull_edges, detached)
        footprint_points = hull[b, i].detach()[..., [0, 2]]
        end, valid = hull_edges(footprint_points, t["hmask"][b, i])
        s = segments_distance(world[b, j][..., [0, 2]], footprint_points, end, valid)  # (S, V)
    else:
        # supporters' footprints (numpy, detached), one per distinct supporter, padded to K by repetition
        hull_np = hull.detach().cpu().double().numpy()
        hmask = t["hmask"].cpu().numpy()
        keys = sorted({(int(bb), int(ii)) for bb, ii in zip(b.tolist(), i.tolist())})
        polys = {k: footprint(hull_np[k[0], k[1]][hmask[k[0], k[1]]][:, [0, 2]]) for k in keys}
        K = max(len(p) for p in polys.values())
        padded = np.stack([np.concatenate([p, np.repeat(p[:1], K - len(p), 0)]) for p in polys.values()])
        index = {k: n for n, k in enumerate(polys)}
        rows = torch.tensor([index[(int(bb), int(ii))] for bb, ii in zip(b.tolist(), i.tolist())], device=world.device)
        polygons = torch.from_numpy(padded).to(world.device, world.dtype)[rows]  # (S, K, 2)
        s = polygon_distance(world[b, j][..., [0, 2]], polygons)  # (S, V)
    outside = t["vmask"][b, j] & (s > OUTSIDE)
    if share:
        return b, (s * outside).sum(-1) / outside.sum(-1).clamp_min(1), outside.sum(-1) / t["vmask"][b, j].sum(-1)
    return b, (s * outside).sum(-1) / outside.sum(-1).clamp_min(1)


def relation_loss(world: torch.Tensor, hull: torch.Tensor, meshes, supports: torch.Tensor,
                  pairs: torch.Tensor | None = None, device: bool = False) -> torch.Tensor:
    """G_R per scene (B,) for posed vertices (B, N, V, 3), their hull vertices (B, N, H, 3) and
    ``supports`` (B, N, N) bool ([b, i, j]: i supports j)."""
    B = world.shape[0]
    out = world.new_zeros(B) + 0 * world.sum()
    found = outside_distances(world, hull, meshes, supports, pairs, device)
    if found is None:
        return out
    b, per_pair = found
    edges = torch.zeros(B, device=world.device, dtype=world.dtype).index_add_(0, b, torch.ones_like(per_pair))
    return out.index_add(0, b, per_pair) / edges.clamp_min(1)


def over_loss(world: torch.Tensor, hull: torch.Tensor, meshes, supports: torch.Tensor,
              bounds: torch.Tensor, pairs: torch.Tensor | None = None, device: bool = False) -> torch.Tensor:
    """G_O per scene (B,): ``½ Σ_{(i,j) ∈ E} d̄_ij²``, d̄_ij the mean distance of j's vertices outside i's
    footprint measured in the normalised state's units (x and z divided by their half-ranges of ``bounds``).

    Not the paper's G_R (which divides by |V_ij|·|E|, so a room of many support pairs moves each object slowly): its
    gradient on a supported object's normalised translation is d̄_ij along the way in, so a step of weight λ
    closes about the fraction λ of that mean distance, whatever the room holds."""
    B = world.shape[0]
    out = world.new_zeros(B) + 0 * world.sum()
    scale = world.new_ones(3)
    scale[[0, 2]] = 0.5 * (bounds[[3, 5]] - bounds[[0, 2]]).to(world)
    found = outside_distances(world / scale, hull / scale, meshes, supports, pairs, device)
    if found is None:
        return out
    b, per_pair = found
    return out.index_add(0, b, 0.5 * per_pair * per_pair)


register_term(GuidanceTerm(
    "relation", lambda ctx: relation_loss(ctx.world, ctx.hull, ctx.meshes, ctx.held, ctx.held_pairs, ctx.on_device),
    description="G_R: supported vertices outside the supporter's xz hull"))
register_term(GuidanceTerm(
    "over", lambda ctx: over_loss(ctx.world, ctx.hull, ctx.meshes, ctx.held, ctx.bounds, ctx.held_pairs,
                          ctx.on_device),
    description="G_O: a supported object's outside vertices drawn over its supporter, the fraction λ per step"))


def home_loss(world: torch.Tensor, hull: torch.Tensor, meshes, supports: torch.Tensor, bounds: torch.Tensor,
              pairs: torch.Tensor | None = None, device: bool = False) -> torch.Tensor:
    """G_home per scene (B,): ``Σ_{(i,j) ∈ E} (d̄_ij + [j wholly outside] · max(0, top_i − low_j))`` in the
    normalised state's units (x, y, z divided by their half-ranges of ``bounds``): d̄_ij the mean distance of j's
    vertices outside i's footprint, top_i the supporter's highest hull point, low_j the supported object's lowest.

    Linear, not quadratic as G_O: its gradient on j's normalised translation is a unit vector (along the way in, and
    up while j is wholly beside and below its supporter's top), so a step of weight λ moves j by λ whatever the
    distance — a cup sampled a metre off its table arrives in the iterations there are, lifted over the table's
    edge rather than driven into its side; j stops once every vertex is over the footprint."""
    B = world.shape[0]
    out = world.new_zeros(B) + 0 * world.sum()
    scale = 0.5 * (bounds[3:] - bounds[:3]).to(world)
    w, h = world / scale, hull / scale
    pairs = supports.nonzero() if pairs is None else pairs
    found = outside_distances(w, h, meshes, supports, pairs, device, share=True)
    if found is None:
        return out
    b, per_pair, share = found
    _, i, j = pairs.unbind(1)
    top = h[b, i, :, 1].detach().amax(-1)  # (S,): padded hull slots repeat a real one (meshes), no mask needed
    low = h[b, j, :, 1].amin(-1)
    wholly = share >= 1  # no vertex of j over i's footprint
    lift = torch.where(wholly, (top - low).clamp_min(0), torch.zeros_like(per_pair))
    return out.index_add(0, b, per_pair + lift)


register_term(GuidanceTerm(
    "home", lambda ctx: home_loss(ctx.world, ctx.hull, ctx.meshes, ctx.held, ctx.bounds, ctx.held_pairs,
                                  ctx.on_device),
    description="G_home: a supported object beside its supporter brought over it at λ a step, lifted over its edge"))
