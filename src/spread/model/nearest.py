"""Exact nearest neighbour on another object, batched over scenes: the hot loop of the geometry features.

Problem: posed point clouds ``world`` (B, N, M, 3) of N objects per scene (``valid`` marks the real
ones); for every point, the index of the nearest point that belongs to a different real object of the
same scene. Brute force is B·(N·M)² distances — 6.4·10⁹ for 4 rooms of 20 objects × 2,000 points —
and on a CPU a distance costs about a memory write, so the search prunes whole objects first:

1. Each object's points are put in Morton (Z-curve) order of their canonical coordinates, so that
   consecutive points form compact surface patches. Queries then go in blocks of at most ``BLOCK``
   consecutive points of one object — one patch — in every scene of the batch at once. The Python
   loops are over such blocks of query points and over chunks inside a block, never over scenes or
   object pairs: candidate objects are found by tensor ops.
2. Upper bound ``U(p)``: the exact distance to a near representative point of another object
   (``REPRESENTATIVES`` per object, a strided subset). Lower bound ``L(p, j)``: the distance from p to
   object j's posed box (the canonical AABB of its points, moved by its pose), computed in j's frame.
   The nearest point lies on an object j with ``L(p, j) ≤ U(p)``: only those are candidates (for the
   block, the union over its queries; for each query the others are masked out).
3. Inside a block, chunks of queries against the candidates' points: ``‖q‖² − 2 p·q`` (one batched
   matmul) and argmin, the distance block kept below ``max_elements`` entries.

The pruning never changes the answer (``prune=False`` searches all other objects and is what the
tests compare against); it only decides how much of the (N·M)² work is done.
"""

from __future__ import annotations

import torch
from einops import rearrange

from spread.data.points import morton_order  # noqa: F401 - the model's name for it

#: Default bound on the entries of one chunk's distance block (float32: 4 bytes each → 64 MiB).
CHUNK_ELEMENTS = 1 << 24
#: Largest block of query points (per scene) that shares one candidate set.
BLOCK = 256
#: Representative points per object used for the upper bound.
REPRESENTATIVES = 32
#: Slack (metres) added to the upper bound so float rounding can never drop the true neighbour's object.
BOUND_SLACK = 1e-4


def query_blocks(num_objects: int, num_points: int, block: int) -> list[tuple[int, int]]:
    """[start, stop) ranges over the flat (N·M) query index, at most ``block`` long, never straddling
    two objects."""
    step = min(num_points, block)
    return [(n * num_points + s, n * num_points + min(s + step, num_points))
            for n in range(num_objects) for s in range(0, num_points, step)]


def _nearest_representative(queries: torch.Tensor, reps: torch.Tensor, excluded: torch.Tensor) -> torch.Tensor:
    """Exact distance (B, Q) from each query (B, Q, 3) to a near representative (B, R, 3) not excluded
    (B, Q, R); inf when all are. Chosen by the matmul form, then measured exactly: an upper bound."""
    d2 = torch.baddbmm((reps * reps).sum(-1)[:, None, :], queries, reps.transpose(1, 2), alpha=-2.0)
    d2.masked_fill_(excluded, float("inf"))
    best = d2.argmin(-1)
    found = reps.gather(1, best[..., None].expand(-1, -1, 3))
    dist = torch.linalg.vector_norm(queries - found, dim=-1)
    return dist.masked_fill(excluded.all(-1), float("inf"))


def _box_distance(queries: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor,
                  lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Distance (B, Q, N) from queries (B, Q, 3) to every object's posed box (canonical lo/hi (B, N, 3))."""
    rel = queries[:, :, None, :] - translation[:, None, :, :]  # (B, Q, N, 3)
    local = (rel[..., :, None] * rotation[:, None]).sum(-2)  # Rᵀ·rel
    gap = (lo[:, None] - local).clamp(min=0) + (local - hi[:, None]).clamp(min=0)
    return torch.linalg.vector_norm(gap, dim=-1)


def _search_block(world: torch.Tensor, queries: torch.Tensor, allowed: torch.Tensor, chunk: int | None,
                  max_elements: int) -> torch.Tensor | None:
    """Flat index (B, Q) into N·M of the nearest point for queries (B, Q, 3) among the objects that
    ``allowed`` (B, Q, N) permits to any query of the block. None when no query has a candidate.

    Searching the union instead of each query's own set cannot change the answer: an object outside
    a query's set is either its own object or a padding one (never in any set of the block, whose
    queries share one owner) or provably farther than that query's nearest point.
    """
    B, N, M, _ = world.shape
    Q = queries.shape[1]
    wanted = allowed.any(1)  # (B, N)
    width = int(wanted.sum(1).max())
    if width == 0:
        return None
    candidates = torch.argsort((~wanted).to(torch.uint8), dim=1, stable=True)[:, :width]  # (B, C)
    usable = wanted.gather(1, candidates)
    rows = (torch.arange(B, device=world.device)[:, None] * N + candidates).view(-1)
    keys = world.reshape(B * N, M * 3).index_select(0, rows).view(B, width, M, 3)
    key_sq = (keys * keys).sum(-1).masked_fill(~usable[..., None], float("inf"))
    # one matmul gives ‖q‖² − 2p·q: keys augmented with ‖q‖², queries with −2p and a 1
    keys_aug = rearrange(torch.cat([keys, key_sq[..., None]], dim=-1), "b c m x -> b x (c m)")
    queries_aug = torch.cat([-2.0 * queries, torch.ones_like(queries[..., :1])], dim=-1)
    step = chunk or max(1, max_elements // (B * width * M))
    out = torch.empty(B, Q, dtype=torch.long, device=world.device)
    for s in range(0, Q, step):
        e = min(s + step, Q)
        best = torch.bmm(queries_aug[:, s:e], keys_aug).argmin(-1)
        out[:, s:e] = candidates.gather(1, best // M) * M + best % M
    return out


def nearest_other_point(world: torch.Tensor, points_local: torch.Tensor, translation: torch.Tensor,
                        rotation: torch.Tensor, valid: torch.Tensor, chunk: int | None = None,
                        max_elements: int = CHUNK_ELEMENTS, prune: bool = True) -> torch.Tensor:
    """(B, N·M) int64 flat index (object·M + point) of each point's nearest point on another real object.

    world (B, N, M, 3) = rotation·points_local + translation; translation (B, N, 3), rotation
    (B, N, 3, 3), valid (B, N) bool. Padding queries, and queries with no other real object in their
    scene, get an arbitrary index (the caller masks them). ``chunk`` caps the queries per scene in one distance
    block (default: as many as ``max_elements`` allows).
    """
    B, N, M, _ = world.shape
    device = world.device
    objects = torch.arange(N, device=device)
    order = morton_order(points_local)  # (B, N, M)
    world = world.gather(2, order[..., None].expand(-1, -1, -1, 3))
    if prune:
        lo, hi = points_local.amin(2), points_local.amax(2)
        r = min(M, REPRESENTATIVES)
        pick = torch.linspace(0, M - 1, r, device=device).long()
        reps = rearrange(world[:, :, pick], "b n r c -> b (n r) c")
    found = torch.zeros(B, N * M, dtype=torch.long, device=device)  # flat index, both in sorted order
    world_flat = world.reshape(B, N * M, 3)
    for start, stop in query_blocks(N, M, BLOCK):  # one object's patch, in every scene at once
        owner = start // M
        queries = world_flat[:, start:stop]  # (B, Q, 3)
        allowed = (valid & (objects != owner) & valid[:, owner, None])[:, None, :].expand(B, stop - start, N)
        if prune:
            excluded = (~allowed)[..., None].expand(-1, -1, -1, r).reshape(B, stop - start, N * r)
            upper = _nearest_representative(queries, reps, excluded)
            lower = _box_distance(queries, translation, rotation, lo, hi)
            allowed = allowed & (lower <= (upper + BOUND_SLACK)[..., None])
        hit = _search_block(world, queries, allowed, chunk, max_elements)
        if hit is not None:
            found[:, start:stop] = hit
    found = found.view(B, N, M)
    # back to the caller's point order: sorted flat index (n, k) → (n, order[n, k]); queries unsorted
    neighbour = found // M
    original = neighbour * M + order.view(B, N * M).gather(1, found.view(B, -1)).view(B, N, M) % M
    nearest = torch.empty_like(original).scatter_(2, order, original)
    return nearest.view(B, N * M)


def nearest_other_point_posed(world: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """:func:`nearest_other_point` of already posed points (B, N, M, 3): each object's frame taken as the world's
    (identity poses, its boxes those of the posed points)."""
    B, N = world.shape[:2]
    eye = torch.eye(3, dtype=world.dtype, device=world.device).expand(B, N, 3, 3)
    return nearest_other_point(world, world, torch.zeros_like(world[:, :, 0]), eye, valid)


#: Relative slack of the tree search's object culling (a box distance in float64 against a float64 tree distance).
TREE_SLACK = 1e-9


def _box_distance2(queries, lo, hi):
    """(R, Q) float64 squared distances from queries (Q, 3) to R axis-aligned boxes ``lo``/``hi`` (R, 3) (zero
    inside); one coordinate at a time over contiguous (R, Q) arrays (numpy: a reduction over a last axis of 3 is
    slow)."""
    import numpy as np

    total = None
    for k in range(3):
        q = queries[None, :, k]
        gap = np.maximum(lo[:, k, None] - q, q - hi[:, k, None])
        np.maximum(gap, 0.0, out=gap)
        np.multiply(gap, gap, out=gap)
        total = gap if total is None else np.add(total, gap, out=total)
    return total


def nearest_other_point_tree(world: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, N·M) int64 flat index (object·M + point) of each point's nearest point on another real object, by one k-d
    tree per object (scipy's ``cKDTree``, on the host; float64 distances of the float32 points: exact, the smallest
    distance whatever the tie). world (B, N, M, 3) posed points, valid (B, N) bool; padding queries and those of an
    object alone in its scene get index 0 (the caller masks them). Non-finite points (diverged poses) go to
    :func:`nearest_other_point` instead, which returns an index for them as it always did.

    For each real object i of a scene, the other real objects are visited nearest world box first (the distance from a
    query to object j's axis-aligned world box is a lower bound of its distance to any point of j); object j is
    searched only for the queries whose lower bound does not exceed their best distance so far, and its tree stops at
    the largest of those bests; once an object's nearest bound exceeds every query's best, no later object is visited.
    The Python loops are over scenes and objects (a few hundred tree calls per batch), the work in the trees: on one
    CPU thread 5–7× faster than :func:`nearest_other_point` at 4 scenes × 20 objects × 1,000–2,000 points, 3.7× at
    the tiny config's 16 × 20 × 256 (``python benchmarks/bench_tree.py``; ``benchmarks/RESULTS.md``, stops 57–58)."""
    import numpy as np
    from scipy.spatial import cKDTree

    B, N, M, _ = world.shape
    points = world.detach().to("cpu", torch.float64).numpy()
    if not np.isfinite(points).all():  # diverged poses: no tree takes them; the pruned search answers as it always did
        return nearest_other_point_posed(world, valid)
    real = valid.detach().cpu().numpy().astype(bool)
    out = np.zeros((B, N * M), dtype=np.int64)
    slack2 = (1 + TREE_SLACK) ** 2
    for b in range(B):
        objects = np.flatnonzero(real[b])
        if len(objects) < 2:
            continue
        lo, hi = points[b, objects].min(1), points[b, objects].max(1)  # (R, 3) world boxes
        trees = [cKDTree(points[b, j]) for j in objects]
        for a, i in enumerate(objects):
            queries = points[b, i]  # (M, 3)
            lower2 = _box_distance2(queries, lo, hi)  # (R, M) squared lower bounds
            lower2[a] = np.inf  # never its own object
            first = lower2.min(1)  # (R,) each object's bound for the nearest of these queries
            best, best2 = np.full(M, np.inf), np.full(M, np.inf)
            index = np.zeros(M, dtype=np.int64)
            for c in np.argsort(first, kind="stable")[:len(objects) - 1]:
                if first[c] > best2.max() * slack2:
                    break  # this object's bound, and every later one's, exceeds every query's best
                need = np.flatnonzero(lower2[c] <= best2 * slack2)
                if need.size == 0:
                    continue
                bound = best[need].max()
                d, k = trees[c].query(queries[need], k=1,
                                      distance_upper_bound=np.inf if np.isinf(bound) else bound * (1 + TREE_SLACK))
                better = d < best[need]
                hit = need[better]
                best[hit], best2[hit] = d[better], d[better] ** 2
                index[hit] = objects[c] * M + k[better]
            out[b, i * M:(i + 1) * M] = index
    return torch.from_numpy(out).to(world.device)
