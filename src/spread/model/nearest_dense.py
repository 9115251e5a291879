"""The geometry features of a denoising step in two operators: pose, then the signed nearest-other-object search.

The same problem as :mod:`spread.model.nearest` and :mod:`spread.model.geometry` — for each of the P = N·M posed
points of a scene, the nearest point of another real object of the same scene, and the distance to it signed by that
point's normal — as two registered custom operators, each one Triton kernel on CUDA:

* ``torch.ops.spread.pose_states(states, offset, scale, points, normals, block)`` → posed points and normals
  (B, N, M, 3) and each object's tile boxes (B, N, KT, 6): a program per tile of ``block`` points of one object
  denormalises the object's translation (``offset + x·scale``, metres), turns its rot6d into a rotation by
  Gram–Schmidt (:func:`spread.data.rotation.rot6d_to_matrix`, the same ε), poses the tile's points and normals and
  writes the tile's axis-aligned box.
* ``torch.ops.spread.signed_nearest(points, normals, boxes, valid, no_neighbour)`` → (index (B, P) int64, signed
  distance (B, P) float32). A program takes ``BLOCK_Q`` query points of one object and keeps, per query, the nearest
  candidate as one int64 (the float32 bits of d², monotonic for d² ≥ 0, above the key's index: one ``min`` gives the
  nearest point and, among exact ties, the smallest index — torch's ``argmin`` rule; ``PACKED_KEYS = False`` keeps d²
  and the index apart, with the same rule). It first visits, in full, the tile of another object whose box centre is
  nearest its queries' box centre (an upper bound for every query), then, object by object, skips an object whose
  tiles are all out of reach (one vector test of its boxes) and visits the tiles of the others whose box can still
  hold a point nearer than the worst current best; only those BLOCK_Q × BLOCK_K distances are computed, as differences
  (``dx² + dy² + dz²`` in float32, no ``‖q‖² − 2p·q`` cancellation). Then it signs each query's distance by the
  neighbour's normal (``(p − q)·n_q ≥ 0``: outside, +) and writes ``no_neighbour`` for an object alone in its scene, 0
  for padding. When each object's points are in Morton order (made once per sample) the tiles are compact surface
  patches and most are skipped; the answer never depends on it.

**CPU** (and CUDA when Triton cannot build a kernel, which is then said once as a warning): the same arithmetic in
torch — posing as :func:`spread.model.poses.pose_points` does; the search on the CPU by the k-d trees of
:mod:`spread.model.nearest` (2.6–51× faster than brute force from 2 × 6 × 64 to 2 × 40 × 256 points, the same
answer; ``benchmarks/RESULTS.md``, stop 60), on CUDA by brute force, all objects of all scenes at once per chunk of
queries, up to ``BRUTE_FORCE_LIMIT`` distances, and beyond by the pruned search (the same answer).

Being registered operators, each is one launch on CUDA, opaque to ``torch.compile`` and to CUDA-graph capture (no
host synchronisation inside), and counted as one by :mod:`spread.model.opcount`. Neither is differentiable:
:func:`spread.model.geometry.signed_distances` uses them when no gradient is wanted (the network's features) and
torch otherwise.
"""

from __future__ import annotations

import warnings

import torch

#: Query points per search program (32: 1.7–1.8× faster than 64 on an H200, RESULTS.md); keys per tile (also the
#: pose kernel's tile of points, so the boxes the search skips by are made for it); warps per search program.
#: ``benchmarks/search_blocks.py`` times other choices on a GPU (any choice gives the same answer).
BLOCK_Q = 32
BLOCK_K = 64
NUM_WARPS = 4
#: How the search keeps each query's nearest: True, one int64 (d²'s float32 bits above the index: one ``min`` a
#: tile); False, d² and the index apart (the tile's ``min`` with its first position, then a nearer-or-smaller-index
#: test) — fewer 64-bit operations a distance. The same answer; ``benchmarks/search_blocks.py`` times both.
PACKED_KEYS = True
#: Relative slack on the culling test (float32 rounding of the box distance can never drop the nearest tile).
CULL_SLACK = 1e-5
#: Added to the Gram–Schmidt norms (spread.data.rotation.EPS).
ROT_EPS = 1e-8
#: CUDA without Triton: larger problems (B·P² distances) go through the pruned exact search instead of brute force.
BRUTE_FORCE_LIMIT = 1 << 28
#: Entries of one chunk of brute force's distance block.
CHUNK_ELEMENTS = 1 << 23


# ---- torch implementations (CPU, and the fallback) ------------------------------------------------------------------
def _brute_force(points: torch.Tensor, valid_point: torch.Tensor, points_per_object: int,
                 max_elements: int = CHUNK_ELEMENTS) -> torch.Tensor:
    """(B, P) exact nearest other-object index by brute force in torch (module docstring)."""
    B, P, _ = points.shape
    owner = torch.arange(P, device=points.device) // points_per_object
    out = torch.zeros(B, P, dtype=torch.long, device=points.device)
    step = max(1, max_elements // max(1, 3 * B * P))
    for s in range(0, P, step):
        e = min(s + step, P)
        diff = points[:, s:e, None, :] - points[:, None, :, :]  # (B, Q, P, 3)
        d2 = diff[..., 0] * diff[..., 0] + diff[..., 1] * diff[..., 1] + diff[..., 2] * diff[..., 2]
        blocked = ~valid_point[:, None, :] | (owner[s:e, None] == owner[None, :])[None]
        out[:, s:e] = d2.masked_fill_(blocked, float("inf")).argmin(-1)
    return out


def _search_torch(points: torch.Tensor, valid: torch.Tensor, points_per_object: int) -> torch.Tensor:
    B, P, _ = points.shape
    world = points.view(B, P // points_per_object, points_per_object, 3)
    if points.device.type == "cpu":  # a k-d tree per object: the CPU's fastest at every size
        from spread.model.nearest import nearest_other_point_tree

        return nearest_other_point_tree(world, valid)
    if B * P * P > BRUTE_FORCE_LIMIT:
        from spread.model.nearest import nearest_other_point_posed

        return nearest_other_point_posed(world, valid)
    return _brute_force(points.float(), valid.repeat_interleave(points_per_object, dim=1), points_per_object)


def sign_distances(points: torch.Tensor, normals: torch.Tensor, index: torch.Tensor, valid: torch.Tensor,
                   points_per_object: int, no_neighbour: float) -> torch.Tensor:
    """(B, P) signed distance of each point (B, P, 3) to its neighbour ``index`` (B, P), by the neighbour's normal
    (B, P, 3): +‖p − q‖ where (p − q)·n_q ≥ 0 (outside), −‖p − q‖ else; ``no_neighbour`` for an object alone in its
    scene, 0 for padding objects (``valid`` (B, N))."""
    gather = index[..., None].expand(-1, -1, 3)
    diff = points - points.gather(1, gather)
    dist = torch.linalg.vector_norm(diff, dim=-1)
    signed = torch.copysign(dist, (diff * normals.gather(1, gather)).sum(-1) + 0.0)  # +0.0: a zero product is +
    count = valid.sum(1, keepdim=True)
    has_other = valid & (count - valid.long() > 0)
    fill = valid.float() * no_neighbour
    per_object = torch.where(has_other[..., None], signed.view(*valid.shape, points_per_object), fill[..., None])
    return per_object.reshape(points.shape[:2])


def pose_torch(states: torch.Tensor, offset: torch.Tensor, scale: torch.Tensor, points: torch.Tensor,
               normals: torch.Tensor, block: int | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Posed points and normals (B, N, M, 3) and tile boxes (B, N, KT, 6) of states (B, N, 9) (module docstring)."""
    from spread.data.rotation import rot6d_to_matrix
    from spread.model.poses import pose_points

    x = states.float()
    R = rot6d_to_matrix(x[..., 3:9])
    world = pose_points(points, torch.addcmul(offset, x[..., :3], scale), R)
    return world, torch.einsum("bnij,bnmj->bnmi", R, normals), tile_boxes(world, block)


def tile_boxes(world: torch.Tensor, block: int | None = None) -> torch.Tensor:
    """(B, N, KT, 6) [min xyz, max xyz] of each object's tiles of ``block`` (None: :data:`BLOCK_K`) consecutive points
    (the last tile padded by repeating the object's last point, which leaves its box unchanged) of posed points
    (B, N, M, 3)."""
    B, N, M, _ = world.shape
    block = BLOCK_K if block is None else block
    KT = -(-M // block)
    padded = world if KT * block == M else torch.cat([world, world[:, :, -1:].expand(B, N, KT * block - M, 3)], 2)
    tiles = padded.view(B, N, KT, block, 3)
    return torch.cat([tiles.amin(3), tiles.amax(3)], -1)


# ---- the Triton kernels (CUDA) --------------------------------------------------------------------------------------
_KERNELS = None
_search_fold = _search_d2 = None  # the search kernel's helpers, made with the kernels
_BROKEN: set[str] = set()  # kernels Triton failed to build or run here (the torch path runs instead)


def _triton_kernels():
    """The kernels (compiled on first use), or None when Triton is not importable."""
    global _KERNELS, _search_fold, _search_d2  # the search kernel's helpers: a kernel resolves names in the module
    if _KERNELS is not None:
        return _KERNELS or None
    try:
        import triton
        import triton.language as tl
    except Exception:  # noqa: BLE001 - any import failure means: no Triton here
        _KERNELS = False
        return None

    @triton.jit
    def pose_kernel(x_ptr, off_ptr, scale_ptr, pts_ptr, nrm_ptr, world_ptr, wnrm_ptr, box_ptr, M, KT,
                    BK: tl.constexpr, EPS: tl.constexpr):
        obj = tl.program_id(0).to(tl.int64)  # b·N + n
        kt = tl.program_id(1)
        s = x_ptr + obj * 9
        tx = tl.load(off_ptr + 0) + tl.load(s + 0) * tl.load(scale_ptr + 0)
        ty = tl.load(off_ptr + 1) + tl.load(s + 1) * tl.load(scale_ptr + 1)
        tz = tl.load(off_ptr + 2) + tl.load(s + 2) * tl.load(scale_ptr + 2)
        a1x, a1y, a1z = tl.load(s + 3), tl.load(s + 4), tl.load(s + 5)
        a2x, a2y, a2z = tl.load(s + 6), tl.load(s + 7), tl.load(s + 8)
        n1 = tl.sqrt(a1x * a1x + a1y * a1y + a1z * a1z) + EPS
        b1x, b1y, b1z = a1x / n1, a1y / n1, a1z / n1
        d = b1x * a2x + b1y * a2y + b1z * a2z
        c2x, c2y, c2z = a2x - d * b1x, a2y - d * b1y, a2z - d * b1z
        n2 = tl.sqrt(c2x * c2x + c2y * c2y + c2z * c2z) + EPS
        b2x, b2y, b2z = c2x / n2, c2y / n2, c2z / n2
        b3x = b1y * b2z - b1z * b2y
        b3y = b1z * b2x - b1x * b2z
        b3z = b1x * b2y - b1y * b2x
        r = kt * BK + tl.arange(0, BK)
        m = r < M
        at = (obj * M + r) * 3
        px = tl.load(pts_ptr + at + 0, mask=m, other=0.0)
        py = tl.load(pts_ptr + at + 1, mask=m, other=0.0)
        pz = tl.load(pts_ptr + at + 2, mask=m, other=0.0)
        wx = b1x * px + b2x * py + b3x * pz + tx
        wy = b1y * px + b2y * py + b3y * pz + ty
        wz = b1z * px + b2z * py + b3z * pz + tz
        tl.store(world_ptr + at + 0, wx, mask=m)
        tl.store(world_ptr + at + 1, wy, mask=m)
        tl.store(world_ptr + at + 2, wz, mask=m)
        nx = tl.load(nrm_ptr + at + 0, mask=m, other=0.0)
        ny = tl.load(nrm_ptr + at + 1, mask=m, other=0.0)
        nz = tl.load(nrm_ptr + at + 2, mask=m, other=0.0)
        tl.store(wnrm_ptr + at + 0, b1x * nx + b2x * ny + b3x * nz, mask=m)
        tl.store(wnrm_ptr + at + 1, b1y * nx + b2y * ny + b3y * nz, mask=m)
        tl.store(wnrm_ptr + at + 2, b1z * nx + b2z * ny + b3z * nz, mask=m)
        inf = float("inf")
        box = box_ptr + (obj * KT + kt) * 6
        tl.store(box + 0, tl.min(tl.where(m, wx, inf), 0))
        tl.store(box + 1, tl.min(tl.where(m, wy, inf), 0))
        tl.store(box + 2, tl.min(tl.where(m, wz, inf), 0))
        tl.store(box + 3, tl.max(tl.where(m, wx, -inf), 0))
        tl.store(box + 4, tl.max(tl.where(m, wy, -inf), 0))
        tl.store(box + 5, tl.max(tl.where(m, wz, -inf), 0))

    @triton.jit
    def _search_fold(best, best_i, d2, k0, BK: tl.constexpr, PACKED: tl.constexpr):
        # each query's nearest so far, with a tile's squared distances d2 (BQ, BK) of keys k0, k0 + 1, …: nearer,
        # or as near with a smaller index (torch's argmin rule). PACKED: best is one int64 a query, d²'s float32 bits
        # above the index (one min); else best (float32 d²) and best_i (int64 index), the tile's min and its first
        # position
        if PACKED:
            ki = k0 + tl.arange(0, BK).to(tl.int64)
            key = (d2.to(tl.int32, bitcast=True).to(tl.int64) << 32) | ki[None, :]
            out, out_i = tl.minimum(best, tl.min(key, 1)), best_i
        else:
            td, pos = tl.min(d2, 1, return_indices=True, return_indices_tie_break_left=True)
            ti = k0 + pos.to(tl.int64)
            take = (td < best) | ((td == best) & (ti < best_i))
            out, out_i = tl.where(take, td, best), tl.where(take, ti, best_i)
        return out, out_i

    @triton.jit
    def _search_d2(best, PACKED: tl.constexpr):
        if PACKED:
            d2 = (best >> 32).to(tl.int32).to(tl.float32, bitcast=True)
        else:
            d2 = best
        return d2

    @triton.jit
    def search_kernel(pts_ptr, nrm_ptr, box_ptr, valid_ptr, idx_ptr, dist_ptr, N, M, KT, QT, NO_NEIGHBOUR,
                      BQ: tl.constexpr, BK: tl.constexpr, SLACK: tl.constexpr, KTP: tl.constexpr,
                      PACKED: tl.constexpr):
        pid = tl.program_id(0)
        b = tl.program_id(1).to(tl.int64)
        o = pid // QT
        r = (pid % QT) * BQ + tl.arange(0, BQ)  # the program's query points, all of object o
        qm = r < M
        P = N * M
        qi = o * M + r
        base = pts_ptr + b * P * 3
        vbase = valid_ptr + b * N
        qx = tl.load(base + qi * 3 + 0, mask=qm, other=0.0)
        qy = tl.load(base + qi * 3 + 1, mask=qm, other=0.0)
        qz = tl.load(base + qi * 3 + 2, mask=qm, other=0.0)
        inf = float("inf")
        qlox = tl.min(tl.where(qm, qx, inf), 0)
        qloy = tl.min(tl.where(qm, qy, inf), 0)
        qloz = tl.min(tl.where(qm, qz, inf), 0)
        qhix = tl.max(tl.where(qm, qx, -inf), 0)
        qhiy = tl.max(tl.where(qm, qy, -inf), 0)
        qhiz = tl.max(tl.where(qm, qz, -inf), 0)
        if PACKED:
            best = tl.full([BQ], 0x7F800000, tl.int64) << 32  # d² = inf, index 0
        else:
            best = tl.full([BQ], float("inf"), tl.float32)
        best_i = tl.zeros([BQ], tl.int64)
        # pass 1: the tile of another real object whose box centre is nearest the query box's centre, in full (an
        # upper bound for every query; half the tiles of an every-S-th-key pass, the same pass 2)
        tiles = tl.arange(0, KTP)
        tm = tiles < KT
        cqx = (qlox + qhix) * 0.5
        cqy = (qloy + qhiy) * 0.5
        cqz = (qloz + qhiz) * 0.5
        seed_d = inf
        seed_t = 0
        for j in range(0, N):
            ok = (j != o) & (tl.load(vbase + j) != 0)
            boxes = box_ptr + ((b * N + j) * KT + tiles) * 6
            cx = (tl.load(boxes + 0, mask=tm, other=0.0) + tl.load(boxes + 3, mask=tm, other=0.0)) * 0.5 - cqx
            cy = (tl.load(boxes + 1, mask=tm, other=0.0) + tl.load(boxes + 4, mask=tm, other=0.0)) * 0.5 - cqy
            cz = (tl.load(boxes + 2, mask=tm, other=0.0) + tl.load(boxes + 5, mask=tm, other=0.0)) * 0.5 - cqz
            cd = tl.where(tm & ok, cx * cx + cy * cy + cz * cz, inf)
            m = tl.min(cd, 0)
            nearer = m < seed_d
            seed_t = tl.where(nearer, j * KT + tl.argmin(cd, 0), seed_t)
            seed_d = tl.where(nearer, m, seed_d)
        if seed_d < inf:
            rk = (seed_t % KT) * BK + tl.arange(0, BK)
            km = rk < M
            ki = (seed_t // KT) * M + rk
            kx = tl.load(base + ki * 3 + 0, mask=km, other=0.0)
            ky = tl.load(base + ki * 3 + 1, mask=km, other=0.0)
            kz = tl.load(base + ki * 3 + 2, mask=km, other=0.0)
            dx = qx[:, None] - kx[None, :]
            dy = qy[:, None] - ky[None, :]
            dz = qz[:, None] - kz[None, :]
            d2 = tl.where(km[None, :], dx * dx + dy * dy + dz * dz, inf)
            k0 = ((seed_t // KT) * M + (seed_t % KT) * BK).to(tl.int64)
            best, best_i = _search_fold(best, best_i, d2, k0, BK, PACKED)
        # pass 2: the tiles of the other real objects whose boxes can still hold a nearer point
        vo = tl.load(vbase + o) != 0
        if vo:
            for j in range(0, N):
                if (j != o) & (tl.load(vbase + j) != 0):
                    worst = tl.max(tl.where(qm, _search_d2(best, PACKED), 0.0), 0)
                    boxes = box_ptr + ((b * N + j) * KT + tiles) * 6
                    tm = tiles < KT
                    vx = tl.maximum(tl.maximum(tl.load(boxes + 0, mask=tm, other=inf) - qhix,
                                               qlox - tl.load(boxes + 3, mask=tm, other=-inf)), 0.0)
                    vy = tl.maximum(tl.maximum(tl.load(boxes + 1, mask=tm, other=inf) - qhiy,
                                               qloy - tl.load(boxes + 4, mask=tm, other=-inf)), 0.0)
                    vz = tl.maximum(tl.maximum(tl.load(boxes + 2, mask=tm, other=inf) - qhiz,
                                               qloz - tl.load(boxes + 5, mask=tm, other=-inf)), 0.0)
                    near = tl.min(vx * vx + vy * vy + vz * vz, 0)
                    kt_end = tl.where(near <= worst * (1.0 + SLACK), KT, 0)
                    for kt in range(0, kt_end):
                        box = box_ptr + ((b * N + j) * KT + kt) * 6
                        gx = tl.maximum(tl.maximum(tl.load(box + 0) - qhix, qlox - tl.load(box + 3)), 0.0)
                        gy = tl.maximum(tl.maximum(tl.load(box + 1) - qhiy, qloy - tl.load(box + 4)), 0.0)
                        gz = tl.maximum(tl.maximum(tl.load(box + 2) - qhiz, qloz - tl.load(box + 5)), 0.0)
                        if gx * gx + gy * gy + gz * gz <= worst * (1.0 + SLACK):
                            rk = kt * BK + tl.arange(0, BK)
                            km = rk < M
                            ki = j * M + rk
                            kx = tl.load(base + ki * 3 + 0, mask=km, other=0.0)
                            ky = tl.load(base + ki * 3 + 1, mask=km, other=0.0)
                            kz = tl.load(base + ki * 3 + 2, mask=km, other=0.0)
                            dx = qx[:, None] - kx[None, :]
                            dy = qy[:, None] - ky[None, :]
                            dz = qz[:, None] - kz[None, :]
                            d2 = tl.where(km[None, :], dx * dx + dy * dy + dz * dz, inf)
                            best, best_i = _search_fold(best, best_i, d2, (j * M + kt * BK).to(tl.int64), BK, PACKED)
                            worst = tl.max(tl.where(qm, _search_d2(best, PACKED), 0.0), 0)
        # every query of an object with another real object has found one (each such object is visited in pass 2)
        found = (_search_d2(best, PACKED) != inf) & vo
        if PACKED:
            best_i = best & 0xFFFFFFFF
        idx = tl.where(found, best_i, 0)
        tl.store(idx_ptr + b * P + qi, idx, mask=qm)
        # the signed distance to the neighbour, by the neighbour's normal
        nx_ = tl.load(base + idx * 3 + 0, mask=qm, other=0.0)
        ny_ = tl.load(base + idx * 3 + 1, mask=qm, other=0.0)
        nz_ = tl.load(base + idx * 3 + 2, mask=qm, other=0.0)
        nbase = nrm_ptr + b * P * 3
        ex = qx - nx_
        ey = qy - ny_
        ez = qz - nz_
        dist = tl.sqrt(ex * ex + ey * ey + ez * ez)
        dot = ex * tl.load(nbase + idx * 3 + 0, mask=qm, other=0.0) \
            + ey * tl.load(nbase + idx * 3 + 1, mask=qm, other=0.0) \
            + ez * tl.load(nbase + idx * 3 + 2, mask=qm, other=0.0)
        signed = tl.where(dot >= 0, dist, -dist)
        lone = tl.where(vo, NO_NEIGHBOUR, 0.0)
        tl.store(dist_ptr + b * P + qi, tl.where(found, signed, lone), mask=qm)

    _KERNELS = (triton, pose_kernel, search_kernel)
    return _KERNELS


def triton_available(device: torch.device) -> bool:
    """Whether the Triton kernels can run on ``device`` (a CUDA device with Triton importable; or any device under
    Triton's interpreter, ``TRITON_INTERPRET=1``, which the tests use on CPU)."""
    import os

    if device.type != "cuda" and os.environ.get("TRITON_INTERPRET") != "1":
        return False
    return _triton_kernels() is not None


def graph_safe(device: torch.device | str) -> bool:
    """Whether the dense search reads nothing on the host on ``device``, so a CUDA graph can record it: on CUDA only
    through its Triton kernel (the torch fallback's pruned search, beyond ``BRUTE_FORCE_LIMIT``, reads its blocks'
    sizes); elsewhere CUDA graphs do not apply (True)."""
    device = torch.device(device)
    return device.type != "cuda" or _use_kernel("search", device)


def _use_kernel(name: str, device: torch.device) -> bool:
    return name not in _BROKEN and triton_available(device)


def _kernel_failed(name: str, error: Exception) -> None:
    _BROKEN.add(name)
    warnings.warn(f"spread.model.nearest_dense: the Triton kernel '{name}' failed here ({type(error).__name__}: "
                  f"{str(error).splitlines()[0] if str(error) else ''}); its torch implementation runs instead "
                  f"(the same answer, more launches)", RuntimeWarning, stacklevel=3)


@torch.library.custom_op("spread::pose_states", mutates_args=())
def pose_states(states: torch.Tensor, offset: torch.Tensor, scale: torch.Tensor, points: torch.Tensor,
                normals: torch.Tensor, block: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Posed points, posed normals (B, N, M, 3) and tile boxes (B, N, KT, 6) of node states (B, N, 9) (normalised
    translation, rot6d), denormalised by ``offset + x·scale`` (metres), canonical points and normals (B, N, M, 3)."""
    B, N, M, _ = points.shape
    if _use_kernel("pose", points.device):
        try:
            triton, pose_kernel, _ = _triton_kernels()
            KT = triton.cdiv(M, block)
            world = torch.empty_like(points, dtype=torch.float32)
            wnormals = torch.empty_like(world)
            boxes = torch.empty(B, N, KT, 6, dtype=torch.float32, device=points.device)
            pose_kernel[(B * N, KT)](states.float().contiguous(), offset.float().contiguous(), scale.float().contiguous(),
                                     points.float().contiguous(), normals.float().contiguous(), world, wnormals, boxes,
                                     M, KT, BK=block, EPS=ROT_EPS)
            return world, wnormals, boxes
        except Exception as error:  # noqa: BLE001 - a kernel Triton cannot build here: the torch path
            _kernel_failed("pose", error)
    return pose_torch(states, offset, scale, points.float(), normals.float(), block)


@pose_states.register_fake
def _(states, offset, scale, points, normals, block):
    B, N, M, _ = points.shape
    KT = -(-M // block)
    return (points.new_empty(points.shape, dtype=torch.float32), points.new_empty(points.shape, dtype=torch.float32),
            points.new_empty((B, N, KT, 6), dtype=torch.float32))


@torch.library.custom_op("spread::signed_nearest", mutates_args=())
def signed_nearest(points: torch.Tensor, normals: torch.Tensor, boxes: torch.Tensor, valid: torch.Tensor,
                   no_neighbour: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(index (B, P) int64, signed distance (B, P) float32) for posed points and normals (B, N, M, 3) of objects
    ``valid`` (B, N): the flat index (object·M + point) of each point's nearest point on another real object, and
    the distance to it signed by its normal (module docstring); ``boxes`` (B, N, KT, 6): :func:`tile_boxes` of the
    points, what the CUDA kernel skips tiles by. Padding objects' points get index 0 and distance 0, those of an
    object alone in its scene index 0 and ``no_neighbour``."""
    B, N, M, _ = points.shape
    valid = valid.bool()
    if boxes.shape[2] != -(-M // BLOCK_K):
        raise ValueError(f"signed_nearest: boxes of {boxes.shape[2]} tiles an object, but BLOCK_K = {BLOCK_K} makes "
                         f"{-(-M // BLOCK_K)} of {M} points (make the boxes with the same block)")
    if _use_kernel("search", points.device):
        try:
            triton, _, search_kernel = _triton_kernels()
            P, QT, KT = N * M, triton.cdiv(M, BLOCK_Q), boxes.shape[2]
            index = torch.empty(B, P, dtype=torch.long, device=points.device)
            distance = torch.empty(B, P, dtype=torch.float32, device=points.device)
            search_kernel[(N * QT, B)](points.float().contiguous(), normals.float().contiguous(), boxes.float().contiguous(),
                                       valid.to(torch.int8).contiguous(), index, distance, N, M, KT, QT,
                                       float(no_neighbour), BQ=BLOCK_Q, BK=BLOCK_K, SLACK=CULL_SLACK,
                                       KTP=triton.next_power_of_2(KT), PACKED=PACKED_KEYS, num_warps=NUM_WARPS)
            return index, distance
        except Exception as error:  # noqa: BLE001
            _kernel_failed("search", error)
    flat = points.float().reshape(B, N * M, 3)
    index = _search_torch(flat, valid, M)
    alone = ~valid | (valid.sum(1, keepdim=True) - valid.long() == 0)
    index = index.masked_fill(alone[:, :, None].expand(B, N, M).reshape(B, N * M), 0)  # index 0, as the kernel
    return index, sign_distances(flat, normals.float().reshape(B, N * M, 3), index, valid, M, float(no_neighbour))


@signed_nearest.register_fake
def _(points, normals, boxes, valid, no_neighbour):
    B, N, M, _ = points.shape
    return (points.new_empty((B, N * M), dtype=torch.long), points.new_empty((B, N * M), dtype=torch.float32))


def nearest_dense_search(world: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, N·M) flat nearest other-object index for posed points ``world`` (B, N, M, 3) of objects ``valid`` (B, N)
    (the search operator; its distances unused)."""
    return torch.ops.spread.signed_nearest(world, torch.zeros_like(world), tile_boxes(world), valid.bool(), 0.0)[0]
