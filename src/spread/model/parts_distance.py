"""The ``parts`` geometry distance: each surface point's signed distance to the other objects' convex parts.

The release's signed chamfer proxy (:mod:`spread.model.geometry`) signs the distance to the nearest *sampled*
point of another object by that point's normal; on furniture made of boards it reads most objects of
collision-free rooms as penetrating (benchmarks/RESULTS.md, "what the geometry features read"). This feature asks
the shapes themselves: for a point p of object i (posed) and every other real object j,

    s_j(p) = min over j's parts k of max over k's planes (n·q − d),   q = R_jᵀ (p − t_j)   (j's canonical frame)

(:mod:`spread.data.parts`: exact sign; inside, minus the depth into the part; outside, a lower bound of the
distance), and d(p) = min(min_j s_j(p), ``PARTS_RANGE``) metres. Beyond ``PARTS_RANGE`` nothing is measured: a
part whose box, posed and grown by the range, misses object i's posed points' box is skipped (so far pairs cost
nothing), and such points read ``PARTS_RANGE``. An object alone in its scene reads ``PARTS_RANGE``; padding 0.

The candidate (scene, i, j, part) quadruples are found on the tensors' device (one ``nonzero`` per call: a host
synchronisation, unlike the chamfer search) and evaluated in chunks of at most ``CHUNK_ELEMENTS`` numbers. No
autograd: the network reads the feature of its input state (as for the chamfer feature).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

#: Largest distance (metres) the feature measures; farther points read this.
PARTS_RANGE = 0.1
#: Most (candidate × point × plane) numbers evaluated at once.
CHUNK_ELEMENTS = 1 << 24


@dataclass
class PartPlanes:
    """The pose-independent part shapes of a batch: planes (B, N, P, F, 4) [unit n, d] and boxes (B, N, P, 2, 3)
    in each object's canonical frame, valid (B, N, P) bool (real objects' real parts only), P trimmed to the
    batch's most parts."""

    planes: torch.Tensor
    boxes: torch.Tensor
    valid: torch.Tensor

    @classmethod
    def from_batch(cls, batch: dict, mask: torch.Tensor) -> "PartPlanes":
        """From a batch's ``part_planes`` / ``part_boxes`` / ``part_valid`` (:mod:`spread.data.parts`)."""
        missing = [k for k in ("part_planes", "part_boxes", "part_valid") if k not in batch]
        if missing:
            raise ValueError(f"geometry_distance=parts: the batch has no {missing} (a dataset built with "
                             f"geometry_distance='parts' carries them)")
        valid = batch["part_valid"].bool() & mask.bool()[..., None]
        used = int(valid.any(1).any(0).nonzero().max()) + 1 if valid.any() else 1
        return cls(batch["part_planes"][:, :, :used].float(), batch["part_boxes"][:, :, :used].float(),
                   valid[:, :, :used])


def posed_boxes(boxes: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """World axis-aligned boxes (B, N, P, 2, 3) of canonical boxes (B, N, P, 2, 3) posed by (B, N, 3), (B, N, 3, 3)."""
    centre, half = boxes.mean(-2), (boxes[..., 1, :] - boxes[..., 0, :]) / 2
    c = torch.einsum("bnij,bnpj->bnpi", rotation, centre) + translation[:, :, None]
    h = torch.einsum("bnij,bnpj->bnpi", rotation.abs(), half)
    return torch.stack([c - h, c + h], dim=-2)


def part_candidates(parts: PartPlanes, world: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor,
                    valid: torch.Tensor, reach: float) -> tuple[torch.Tensor, ...]:
    """(b, i, j, k) flat indices of every (scene, object i, other real object j, j's part k) whose posed part box,
    grown by ``reach`` metres, meets the box of i's posed points ``world`` (B, N, M, 3) — one ``nonzero``."""
    N = world.shape[1]
    lo, hi = world.amin(2), world.amax(2)  # (B, N, 3) each object's points' box
    part_box = posed_boxes(parts.boxes, translation, rotation)  # (B, N, P, 2, 3)
    near = ((lo[:, :, None, None] <= part_box[:, None, :, :, 1] + reach)
            & (hi[:, :, None, None] >= part_box[:, None, :, :, 0] - reach)).all(-1)  # (B, Ni, Nj, P)
    others = valid[:, :, None] & valid[:, None, :] & ~torch.eye(N, dtype=torch.bool, device=world.device)
    return (near & others[..., None] & parts.valid[:, None]).nonzero(as_tuple=True)


def part_values(parts: PartPlanes, world: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor,
                candidates: tuple[torch.Tensor, ...], max_elements: int = CHUNK_ELEMENTS):
    """For the ``candidates`` (b, i, j, k) of :func:`part_candidates`, in chunks of at most ``max_elements``
    (candidate × point × plane) numbers: yields (chunk's slice, s (C, M)), s = max over part k's planes of
    (n·q − d) at each of i's points q = R_jᵀ (p − t_j) in j's canonical frame (< 0 inside, minus the depth)."""
    b, i, j, k = candidates
    M, F = world.shape[2], parts.planes.shape[-2]
    step = max(1, max_elements // (M * F))
    for start in range(0, len(b), step):
        chunk = slice(start, start + step)
        bb, ii, jj, kk = b[chunk], i[chunk], j[chunk], k[chunk]
        local = torch.einsum("cmi,cij->cmj", world[bb, ii] - translation[bb, jj][:, None], rotation[bb, jj])
        planes = parts.planes[bb, jj, kk]  # (C, F, 4)
        yield chunk, (torch.einsum("cmj,cfj->cmf", local, planes[..., :3]) - planes[:, None, :, 3]).amax(-1)


@torch.no_grad()
def parts_distances(parts: PartPlanes, world: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor,
                    valid: torch.Tensor, reach: float = PARTS_RANGE, max_elements: int = CHUNK_ELEMENTS,
                    pairs: bool = False) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
    """(B, N, M) signed distance (metres, at most ``reach``) of every posed point ``world`` (B, N, M, 3) to the other
    real objects' parts posed by translation (B, N, 3), rotation (B, N, 3, 3) world-from-local; valid (B, N).

    With ``pairs``, also (B, N, N): for each ordered pair (i, j), the signed distance of i's deepest point with
    respect to j alone (min over i's points and j's parts, at most ``reach``; ``reach`` on the diagonal and for a
    padding object) — what the per-point distance, a minimum over every other object, cannot tell apart."""
    B, N, M, _ = world.shape
    world, t, R = world.float(), translation.float(), rotation.float()
    candidates = part_candidates(parts, world, t, R, valid, reach)
    b, i, j = candidates[0], candidates[1], candidates[2]
    out = torch.full((B * N, M), float(reach), device=world.device)
    pair = torch.full((B * N * N,), float(reach), device=world.device) if pairs else None
    for chunk, s in part_values(parts, world, t, R, candidates, max_elements):
        out.scatter_reduce_(0, (b[chunk] * N + i[chunk])[:, None].expand(-1, M), s, "amin")
        if pair is not None:
            pair.scatter_reduce_(0, (b[chunk] * N + i[chunk]) * N + j[chunk], s.amin(-1), "amin")
    out = torch.where(valid[..., None], out.clamp(max=reach).view(B, N, M), 0.0)
    if pair is None:
        return out
    return out, pair.clamp(max=reach).view(B, N, N)
