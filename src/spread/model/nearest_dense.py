"""The dense nearest-other-object point search: one operator, no Python loop over blocks or objects.

Same problem as :mod:`spread.model.nearest` — for each of the P = N·M posed points of a scene, the index of the
nearest point that belongs to another real object of the same scene — as one custom operator,
``torch.ops.spread.nearest_dense(points, boxes, valid, points_per_object)``:

* **CUDA** (with Triton, which ships with torch on Linux): one Triton kernel. A program takes ``BLOCK_Q`` query
  points of one object of one scene and keeps, per query, the nearest candidate as one int64 (the float32 bits of d²,
  monotonic for d² ≥ 0, above the key's index: one ``min`` gives the nearest point and, among exact ties, the
  smallest index — torch's ``argmin`` rule). It first visits every ``STRIDE``-th key of the scene (an upper bound
  for every query), then, object by object, every tile of ``BLOCK_K`` consecutive points of another real object
  whose box (``boxes``: :func:`tile_boxes`, four torch operators before the launch) can still hold a point nearer
  than the worst current best of the program's queries; only those tiles' BLOCK_Q × BLOCK_K distances are computed.
  Distances are differences, ``dx² + dy² + dz²`` in float32 (no ``‖q‖² − 2p·q`` cancellation). When each object's
  points are in a spatially coherent order (Morton order: :func:`spread.model.nearest.morton_order`, done once per
  sample by the network) the tiles are compact surface patches and most are skipped; the answer never depends on
  it. (``SPREAD_NEAREST_KERNEL=tiles`` runs the first version of the kernel, for comparison.)
* **CPU** (and CUDA without Triton): the same exact arithmetic in torch, all objects of all scenes at once per
  chunk of queries (``max_elements`` bounds a chunk's distance block) for small problems; beyond
  ``BRUTE_FORCE_LIMIT`` distances the exact pruned search of :mod:`spread.model.nearest` (the answer is the same,
  the CPU does not have the arithmetic for brute force at paper size).

Being one registered operator, it is one launch on CUDA, opaque to ``torch.compile`` and to CUDA-graph capture
(no host synchronisation inside), and counted as one by :mod:`spread.model.opcount`.
"""

from __future__ import annotations

import torch

#: Query points per Triton program and keys per tile.
BLOCK_Q = 64
BLOCK_K = 64
#: The first pass of the kernel visits every STRIDE-th key (an upper bound for every query).
STRIDE = 16
#: Relative slack on the culling test (float32 rounding of the box distance can never drop the nearest tile).
CULL_SLACK = 1e-5
#: The CUDA kernel: "objects" (a program per tile of one object's points; other objects' tiles skipped by their
#: boxes) or "tiles" (the first version: tiles over the flat point list, boxes from the loaded keys).
KERNEL = "objects"
#: CPU: larger problems (B·P² distances) go through the pruned exact search instead of brute force.
BRUTE_FORCE_LIMIT = 1 << 28
#: CPU: entries of one chunk's distance block.
CHUNK_ELEMENTS = 1 << 23


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


def _pruned(points: torch.Tensor, valid: torch.Tensor, points_per_object: int) -> torch.Tensor:
    """The pruned exact search on flat points: each object's frame taken as the world's (identity poses)."""
    from spread.model.nearest import nearest_other_point

    B, P, _ = points.shape
    N = P // points_per_object
    world = points.view(B, N, points_per_object, 3)
    eye = torch.eye(3, dtype=points.dtype, device=points.device).expand(B, N, 3, 3)
    zero = torch.zeros(B, N, 3, dtype=points.dtype, device=points.device)
    return nearest_other_point(world, world, zero, eye, valid)


# ---- the Triton kernel (CUDA) --------------------------------------------------------------------------------
_KERNEL = None


def _triton_kernel():
    """The compiled-on-first-use Triton kernel, or None when Triton is not importable."""
    global _KERNEL
    if _KERNEL is not None:
        return _KERNEL or None
    try:
        import triton
        import triton.language as tl
    except Exception:  # noqa: BLE001 - any import failure means: no Triton here
        _KERNEL = False
        return None

    @triton.jit
    def nearest_kernel(pts_ptr, valid_ptr, out_ptr, P, M, N,
                       BQ: tl.constexpr, BK: tl.constexpr, S: tl.constexpr, SLACK: tl.constexpr):
        pid = tl.program_id(0)
        b = tl.program_id(1).to(tl.int64)
        qi = pid * BQ + tl.arange(0, BQ)
        qm = qi < P
        base = pts_ptr + b * P * 3
        qx = tl.load(base + qi * 3 + 0, mask=qm, other=0.0)
        qy = tl.load(base + qi * 3 + 1, mask=qm, other=0.0)
        qz = tl.load(base + qi * 3 + 2, mask=qm, other=0.0)
        qobj = qi // M
        inf = float("inf")
        qlox = tl.min(tl.where(qm, qx, inf), 0)
        qloy = tl.min(tl.where(qm, qy, inf), 0)
        qloz = tl.min(tl.where(qm, qz, inf), 0)
        qhix = tl.max(tl.where(qm, qx, -inf), 0)
        qhiy = tl.max(tl.where(qm, qy, -inf), 0)
        qhiz = tl.max(tl.where(qm, qz, -inf), 0)
        first_obj = (pid * BQ) // M
        last_obj = (tl.minimum(pid * BQ + BQ, P) - 1) // M
        best = tl.full([BQ], inf, tl.float32)
        arg = tl.zeros([BQ], tl.int32)
        vbase = valid_ptr + b * N
        # pass 1: every S-th key, an upper bound for every query
        for k0 in range(0, P, BK * S):
            ki = k0 + tl.arange(0, BK) * S
            km = ki < P
            kobj = ki // M
            kval = km & (tl.load(vbase + kobj, mask=km, other=0) != 0)
            kx = tl.load(base + ki * 3 + 0, mask=km, other=0.0)
            ky = tl.load(base + ki * 3 + 1, mask=km, other=0.0)
            kz = tl.load(base + ki * 3 + 2, mask=km, other=0.0)
            dx = qx[:, None] - kx[None, :]
            dy = qy[:, None] - ky[None, :]
            dz = qz[:, None] - kz[None, :]
            d2 = dx * dx + dy * dy + dz * dz
            d2 = tl.where(kval[None, :] & (kobj[None, :] != qobj[:, None]), d2, inf)
            m = tl.min(d2, 1)
            a = tl.argmin(d2, 1).to(tl.int32)
            a = (k0 + a * S).to(tl.int32)
            better = (m < best) | ((m == best) & (a < arg))
            best = tl.where(better, m, best)
            arg = tl.where(better, a, arg)
        # pass 2: every tile that can still hold a nearer point (its box, from its loaded real keys)
        for k0 in range(0, P, BK):
            ki = k0 + tl.arange(0, BK)
            km = ki < P
            kobj = ki // M
            kval = km & (tl.load(vbase + kobj, mask=km, other=0) != 0)
            kx = tl.load(base + ki * 3 + 0, mask=km, other=0.0)
            ky = tl.load(base + ki * 3 + 1, mask=km, other=0.0)
            kz = tl.load(base + ki * 3 + 2, mask=km, other=0.0)
            gx = tl.maximum(tl.maximum(tl.min(tl.where(kval, kx, inf), 0) - qhix,
                                       qlox - tl.max(tl.where(kval, kx, -inf), 0)), 0.0)
            gy = tl.maximum(tl.maximum(tl.min(tl.where(kval, ky, inf), 0) - qhiy,
                                       qloy - tl.max(tl.where(kval, ky, -inf), 0)), 0.0)
            gz = tl.maximum(tl.maximum(tl.min(tl.where(kval, kz, inf), 0) - qhiz,
                                       qloz - tl.max(tl.where(kval, kz, -inf), 0)), 0.0)
            reach = gx * gx + gy * gy + gz * gz  # inf for a tile without real keys
            worst = tl.max(tl.where(qm, best, 0.0), 0)
            k_first = k0 // M
            k_last = (tl.minimum(k0 + BK, P) - 1) // M
            own = (k_first == k_last) & (first_obj == last_obj) & (k_first == first_obj)
            if (reach <= worst * (1.0 + SLACK)) & (own == 0):
                dx = qx[:, None] - kx[None, :]
                dy = qy[:, None] - ky[None, :]
                dz = qz[:, None] - kz[None, :]
                d2 = dx * dx + dy * dy + dz * dz
                d2 = tl.where(kval[None, :] & (kobj[None, :] != qobj[:, None]), d2, inf)
                m = tl.min(d2, 1)
                a = (k0 + tl.argmin(d2, 1)).to(tl.int32)
                better = (m < best) | ((m == best) & (a < arg))
                best = tl.where(better, m, best)
                arg = tl.where(better, a, arg)
        tl.store(out_ptr + b * P + qi, arg.to(tl.int64), mask=qm)

    @triton.jit
    def objects_kernel(pts_ptr, box_ptr, valid_ptr, out_ptr, N, M, KT, QT,
                       BQ: tl.constexpr, BK: tl.constexpr, S: tl.constexpr, SLACK: tl.constexpr, KTP: tl.constexpr):
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
        # a candidate is one int64: the float32 bits of d² (monotonic for d² ≥ 0) above the key index, so one min
        # gives the nearest point and, among equal distances, the smallest index
        none = tl.full([BQ], 0x7F800000, tl.int64) << 32  # d² = inf, index 0
        best = none
        # pass 1: every S-th key of the scene, an upper bound for every query
        for k0 in range(0, P, BK * S):
            ki = k0 + tl.arange(0, BK) * S
            km = ki < P
            kobj = ki // M
            kval = km & (kobj != o) & (tl.load(vbase + kobj, mask=km, other=0) != 0)
            kx = tl.load(base + ki * 3 + 0, mask=km, other=0.0)
            ky = tl.load(base + ki * 3 + 1, mask=km, other=0.0)
            kz = tl.load(base + ki * 3 + 2, mask=km, other=0.0)
            dx = qx[:, None] - kx[None, :]
            dy = qy[:, None] - ky[None, :]
            dz = qz[:, None] - kz[None, :]
            d2 = tl.where(kval[None, :], dx * dx + dy * dy + dz * dz, inf)
            key = (d2.to(tl.int32, bitcast=True).to(tl.int64) << 32) | ki.to(tl.int64)[None, :]
            best = tl.minimum(best, tl.min(key, 1))
        # pass 2: every tile of every other real object whose box can still hold a nearer point; an object whose
        # tiles are all out of reach (one vector test of its KT boxes) is passed over whole
        tiles = tl.arange(0, KTP)
        if tl.load(vbase + o) != 0:
            for j in range(0, N):
                if (j != o) & (tl.load(vbase + j) != 0):
                    worst = tl.max(tl.where(qm, (best >> 32).to(tl.int32).to(tl.float32, bitcast=True), 0.0), 0)
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
                            key = (d2.to(tl.int32, bitcast=True).to(tl.int64) << 32) | ki.to(tl.int64)[None, :]
                            best = tl.minimum(best, tl.min(key, 1))
                            worst = tl.max(tl.where(qm, (best >> 32).to(tl.int32).to(tl.float32, bitcast=True),
                                                    0.0), 0)
        tl.store(out_ptr + b * P + qi, best & 0xFFFFFFFF, mask=qm)

    _KERNEL = (triton, nearest_kernel, objects_kernel)
    return _KERNEL


def triton_available(device: torch.device) -> bool:
    """Whether the Triton kernel can run on ``device`` (a CUDA device with Triton importable; or any device
    under Triton's interpreter, ``TRITON_INTERPRET=1``, which the tests use on CPU)."""
    import os

    if device.type != "cuda" and os.environ.get("TRITON_INTERPRET") != "1":
        return False
    return _triton_kernel() is not None


def _run_triton(points: torch.Tensor, boxes: torch.Tensor, valid: torch.Tensor, points_per_object: int) -> torch.Tensor:
    import os

    triton, tiles_kernel, objects_kernel = _triton_kernel()
    B, P, _ = points.shape
    N, M = valid.shape[1], points_per_object
    out = torch.empty(B, P, dtype=torch.long, device=points.device)
    valid8 = valid.to(torch.int8).contiguous()
    if os.environ.get("SPREAD_NEAREST_KERNEL", KERNEL) == "tiles":  # the first kernel (kept for comparison)
        tiles_kernel[(triton.cdiv(P, BLOCK_Q), B)](points.contiguous(), valid8, out, P, M, N, BQ=BLOCK_Q, BK=BLOCK_K,
                                                  S=STRIDE, SLACK=CULL_SLACK)
        return out
    QT = triton.cdiv(M, BLOCK_Q)
    objects_kernel[(N * QT, B)](points.contiguous(), boxes.contiguous(), valid8, out, N, M, boxes.shape[2], QT,
                                BQ=BLOCK_Q, BK=BLOCK_K, S=STRIDE, SLACK=CULL_SLACK,
                                KTP=triton.next_power_of_2(boxes.shape[2]))
    return out


@torch.library.custom_op("spread::nearest_dense", mutates_args=())
def nearest_dense(points: torch.Tensor, boxes: torch.Tensor, valid: torch.Tensor, points_per_object: int) -> torch.Tensor:
    """(B, P) int64: for each point of ``points`` (B, P = N·M, 3) float32, the flat index of the nearest point of
    another real object of its scene (object of point k: k // points_per_object; ``valid`` (B, N) bool real
    objects; ``boxes`` (B, N, KT, 6): :func:`tile_boxes`, what the kernel skips tiles by).
    Points of padding objects, and of objects alone in their scene, get an arbitrary index."""
    valid = valid.bool()
    if triton_available(points.device):
        return _run_triton(points.float(), boxes.float(), valid, points_per_object)
    B, P, _ = points.shape
    if B * P * P > BRUTE_FORCE_LIMIT and points.device.type == "cpu":
        return _pruned(points, valid, points_per_object)
    valid_point = valid.repeat_interleave(points_per_object, dim=1)
    return _brute_force(points.float(), valid_point, points_per_object)


@nearest_dense.register_fake
def _(points, boxes, valid, points_per_object):
    return points.new_empty(points.shape[:2], dtype=torch.long)


def nearest_dense_search(world: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """(B, N·M) flat nearest other-object index for posed points ``world`` (B, N, M, 3) and real objects ``valid``
    (B, N): the one operator."""
    B, N, M, _ = world.shape
    return torch.ops.spread.nearest_dense(world.reshape(B, N * M, 3), tile_boxes(world), valid.bool(), M)


def tile_boxes(world: torch.Tensor, block: int = BLOCK_K) -> torch.Tensor:
    """(B, N, KT, 6) [min xyz, max xyz] of each object's tiles of ``block`` consecutive points (the last tile padded
    by repeating the object's last point, which leaves its box unchanged) of posed points (B, N, M, 3)."""
    B, N, M, _ = world.shape
    KT = -(-M // block)
    padded = world if KT * block == M else torch.cat([world, world[:, :, -1:].expand(B, N, KT * block - M, 3)], 2)
    tiles = padded.view(B, N, KT, block, 3)
    return torch.cat([tiles.amin(3), tiles.amax(3)], -1)
