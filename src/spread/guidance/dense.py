"""The guidance's geometry found with tensor operations, on the states' device (``guidance.detect: device``).

The host path (``detect: host``) finds what the guidance terms differentiate through on the CPU: colliding
triangle pairs with python-fcl's BVHs (:class:`spread.guidance.collision.TriangleCollider`, float64 host copies of
the poses every step) and the supporters' footprints with scipy's convex hull, one supporter at a time
(:func:`spread.guidance.relation.footprint`). On a GPU every step then waits for a device → host copy and a Python
loop. This module finds the same things where the poses are, in a fixed number of batched operations:

* :func:`triangle_pairs` — object pairs whose world AABBs overlap (the broad phase both paths share), then, per
  object pair, every (face of i, face of j) pair whose triangle AABBs overlap, then the exact separating-axis test
  of two triangles (:func:`triangles_intersect`, the 17 axes the release's BVH tests: both normals, the 9 edge ×
  edge directions, the 6 in-plane edge normals). Touching counts as intersecting. The pairs are those python-fcl
  reports (tests compare them) but for triangles that only touch, where the two tests may disagree (flush faces
  too: coplanar within rounding, as two boxes at one height overlapping sideways have; their steps can then differ
  widely, docs/DESIGN.md §7); at most
  ``max_contacts`` per object pair, the first in (face of i, face of j) order (fcl keeps the first its traversal
  meets). Memory is bounded by doing the object pairs in chunks of ``CHUNK_ELEMENTS`` triangle pairs, and their
  candidate triangle pairs ``CANDIDATES`` at a time (interpenetrating early predictions have millions).
* :func:`hull_edges` — the edges of the convex hull in (x, z) of each supporter's hull vertices: from each point,
  the edge to the point the most clockwise seen from it, kept when every point lies on its left (within
  ``tolerance``). :func:`spread.guidance.relation.segments_distance` measures a point's distance outside the hull on
  those edges. The same polygon as scipy's (tests), but for a supporter whose points are all collinear (scipy's
  path falls back to their bounding rectangle; here it is their segment).

Host reads that remain per collision evaluation (data-dependent sizes, ``nonzero``): one for the overlapping object
pairs and two per chunk of them (the candidate and the intersecting triangle pairs); the footprints need none. Units: metres, the world frame (y up).
"""

from __future__ import annotations

import torch

from spread.guidance.collision import TrianglePairs, overlapping_pairs

#: Triangle pairs (object pairs × F × F) tested per chunk, by device type; bounds the broad phase's memory (~10
#: bytes each: 640 MiB on a GPU, where fewer, larger chunks mean fewer launches and host reads).
CHUNK_ELEMENTS = {"cpu": 1 << 23, "cuda": 1 << 26}
#: Candidate triangle pairs given to one separating-axis test call (~0.8 kB of temporaries each: 1.6 GiB at most).
CANDIDATES = 1 << 21
#: An edge × edge axis whose |a × b| is below this fraction of |a| |b| (nearly parallel edges) is skipped.
PARALLEL = 1e-9


def resolve_detect(detect: str, device: torch.device | str) -> str:
    """``host`` or ``device`` for the setting ``guidance.detect`` on ``device`` (``auto``: the device's path on
    CUDA, the host's — python-fcl, scipy — on the CPU, where they are faster)."""
    if detect == "auto":
        return "device" if torch.device(device).type == "cuda" else "host"
    return detect


def triangles_intersect(t1: torch.Tensor, t2: torch.Tensor) -> torch.Tensor:
    """(P,) bool: does triangle t1[p] (P, 3, 3) [corner, xyz] meet triangle t2[p] (closed sets: touching counts)?

    Separating-axis test over the 17 axes that decide it for two triangles (coplanar ones included); an axis of
    two nearly parallel edges (``PARALLEL``) is skipped, as its direction is noise."""
    e1 = torch.roll(t1, -1, dims=1) - t1  # (P, 3, 3) edges
    e2 = torch.roll(t2, -1, dims=1) - t2
    n1 = torch.linalg.cross(e1[:, 0], e1[:, 1], dim=-1)
    n2 = torch.linalg.cross(e2[:, 0], e2[:, 1], dim=-1)
    ee = torch.linalg.cross(e1[:, :, None, :].expand(-1, 3, 3, 3), e2[:, None, :, :].expand(-1, 3, 3, 3), dim=-1)
    ee = ee.reshape(-1, 9, 3)
    lengths = (e1 * e1).sum(-1)[:, :, None] * (e2 * e2).sum(-1)[:, None, :]  # |a|² |b|² (P, 3, 3)
    usable = torch.ones(t1.shape[0], 17, dtype=torch.bool, device=t1.device)
    usable[:, 2:11] = (ee * ee).sum(-1) > PARALLEL ** 2 * lengths.reshape(-1, 9)
    axes = torch.cat([n1[:, None], n2[:, None], ee,
                      torch.linalg.cross(n1[:, None, :].expand(-1, 3, 3), e1, dim=-1),
                      torch.linalg.cross(n2[:, None, :].expand(-1, 3, 3), e2, dim=-1)], 1)  # (P, 17, 3)
    p1 = torch.einsum("pkc,pvc->pkv", axes, t1)
    p2 = torch.einsum("pkc,pvc->pkv", axes, t2)
    apart = (p1.amax(-1) < p2.amin(-1)) | (p2.amax(-1) < p1.amin(-1))
    return ~(apart & usable).any(-1)


def _first_hits(k: torch.Tensor, hit: torch.Tensor, limit: int) -> torch.Tensor:
    """Keep-mask (P,) of the hits among candidates with sorted group ids ``k`` (P,): each group's first ``limit``."""
    pos = torch.arange(k.numel(), device=k.device)
    start = torch.ones_like(hit)
    start[1:] = k[1:] != k[:-1]
    count = torch.cumsum(hit.long(), 0)  # hits up to and including each candidate
    before = count - hit.long()  # hits before it
    first = torch.cummax(torch.where(start, pos, torch.zeros_like(pos)), 0).values  # its group's first candidate
    return hit & (count - before[first] <= limit)


def triangle_pairs(world: torch.Tensor, meshes, lo: torch.Tensor, hi: torch.Tensor, mask: torch.Tensor,
                   max_contacts: int) -> TrianglePairs:
    """Colliding triangle pairs between different objects (module docstring) for posed vertices ``world``
    (B, N, V, 3), the objects' world AABBs ``lo``/``hi`` (B, N, 3) and ``mask`` (B, N); not differentiable. The
    pairs' index tensors live on ``world``'s device."""
    world = world.detach()
    t = meshes.tensors(world.device, world.dtype)
    objects = overlapping_pairs(lo.detach(), hi.detach(), mask.to(world.device))
    if not len(objects):
        return TrianglePairs.empty()
    F = t["faces"].shape[2]
    chunk = max(1, CHUNK_ELEMENTS.get(world.device.type, CHUNK_ELEMENTS["cpu"]) // (F * F))
    found = []
    for start in range(0, len(objects), chunk):
        b, i, j = objects[start:start + chunk].unbind(1)
        K = b.numel()
        rows = torch.arange(K, device=world.device)[:, None, None]
        tri_i = world[b, i][rows, t["faces"][b, i]]  # (K, F, 3, 3)
        tri_j = world[b, j][rows, t["faces"][b, j]]
        lo_i, hi_i = tri_i.amin(2), tri_i.amax(2)  # (K, F, 3)
        lo_j, hi_j = tri_j.amin(2), tri_j.amax(2)
        # a face can meet the other object only inside that object's box
        near_i = t["fvalid"][b, i] & ((lo_i <= hi[b, j][:, None]) & (hi_i >= lo[b, j][:, None])).all(-1)
        near_j = t["fvalid"][b, j] & ((lo_j <= hi[b, i][:, None]) & (hi_j >= lo[b, i][:, None])).all(-1)
        boxes = near_i[:, :, None] & near_j[:, None, :]
        boxes &= ((lo_i[:, :, None] <= hi_j[:, None]) & (hi_i[:, :, None] >= lo_j[:, None])).all(-1)
        k, fi, fj = boxes.nonzero().unbind(1)  # in (object pair, fi, fj) order
        if not k.numel():
            continue
        hit = torch.cat([triangles_intersect(tri_i[k[c:c + CANDIDATES], fi[c:c + CANDIDATES]],
                                             tri_j[k[c:c + CANDIDATES], fj[c:c + CANDIDATES]])
                         for c in range(0, k.numel(), CANDIDATES)])
        keep = _first_hits(k, hit, max_contacts).nonzero()[:, 0]
        k, fi, fj = k[keep], fi[keep], fj[keep]
        found.append(torch.stack([b[k], i[k], fi, j[k], fj], 1))
    if not found:
        return TrianglePairs.empty(len(objects))
    rows = torch.cat(found)
    return TrianglePairs(*rows.unbind(1), object_pairs=len(objects))


def hull_edges(points: torch.Tensor, mask: torch.Tensor, tolerance: float | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Counter-clockwise convex-hull edges of point sets ``points`` (S, H, 2) [x, z] with real slots ``mask``
    (S, H): (end (S, H, 2), valid (S, H)) of the edge from each point a (``points[:, a]``) to the point b the most
    clockwise seen from a (angles measured from the direction to the points' mean, which lies inside the hull), kept
    when every real point lies left of a → b within ``tolerance`` metres: then a is a hull vertex and a → b the
    hull's next edge (or part of it, when points are collinear on it). O(H²) per set. ``tolerance`` defaults to
    1e-9 m (float64) or 1e-5 m (lower precision)."""
    if tolerance is None:
        tolerance = 1e-9 if points.dtype == torch.float64 else 1e-5
    weight = mask.to(points.dtype)[..., None]
    centre = (points * weight).sum(1) / weight.sum(1).clamp_min(1)  # (S, 2)
    to_k = points[:, None, :, :] - points[:, :, None, :]  # (S, a, k, 2): k − a
    to_c = (centre[:, None, :] - points)[:, :, None, :]  # (S, a, 1, 2)
    cross = to_c[..., 0] * to_k[..., 1] - to_c[..., 1] * to_k[..., 0]
    angle = torch.atan2(cross, (to_c * to_k).sum(-1))  # (S, a, k), from the way to the centre, counter-clockwise +
    length = to_k.norm(dim=-1)
    usable = mask[:, None, :] & (length > tolerance)
    b = torch.where(usable, angle, torch.full_like(angle, torch.inf)).argmin(-1)  # (S, a)
    end = torch.gather(points, 1, b[..., None].expand(-1, -1, 2))
    edge = end - points  # (S, a, 2)
    # every real point k left of a → b: cross(e, k − a) ≥ −tolerance · |e|
    left = edge[:, :, None, 0] * to_k[..., 1] - edge[:, :, None, 1] * to_k[..., 0]
    ok = (left >= -tolerance * edge.norm(dim=-1)[..., None]) | ~mask[:, None, :]
    valid = mask & usable.any(-1) & ok.all(-1)
    return end, valid
