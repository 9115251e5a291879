"""Tile evaluations of the nearest-point search kernel's algorithm, simulated in torch on the CPU (no GPU needed).

The CUDA kernel (`spread.model.nearest_dense`) gives each program BLOCK_Q query points of one object; its cost is the
number of BLOCK_Q × BLOCK_K distance tiles it evaluates: a first pass that sets an upper bound for every query, then
the tiles of other objects whose boxes can still hold a nearer point. This script replays those decisions exactly
(the same boxes, the same culling test) on synthetic rooms of boxes (bench_model's rooms, Morton-ordered points), at
their poses ("rest") and at noise poses (a sampler's first steps), for two first passes:

* ``stride``: every 16th key of the scene (the kernel before stop 40);
* ``neartile``: the one tile of another object whose box centre is nearest the query box's centre (the kernel now);

and reports the tiles per program in each pass, and the fewest any order could visit (the tiles whose box lies within
the final worst distance of the program's queries).

    python benchmarks/search_tiles.py                 # B = 2 rooms of 20 objects × 1,984 points: ~10 minutes
    python benchmarks/search_tiles.py --objects 8 --points 512
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))


def box_gap2(qlo, qhi, blo, bhi):
    g = torch.clamp(torch.maximum(blo - qhi, qlo - bhi), min=0.0)
    return (g * g).sum(-1)


def simulate(world: torch.Tensor, first: str, BQ: int = 64, BK: int = 64, S: int = 16, slack: float = 1e-5) -> dict:
    """Mean tiles per program of each pass for posed points ``world`` (B, N, M, 3), M a multiple of BQ and BK."""
    from spread.model.nearest_dense import tile_boxes

    B, N, M, _ = world.shape
    P, QT, KT = N * M, M // BQ, M // BK
    flat = world.reshape(B, P, 3)
    tiles = tile_boxes(world, BK)
    tlo, thi = tiles[..., :3], tiles[..., 3:]
    q = world.view(B, N, QT, BQ, 3)
    qlo, qhi = q.amin(3), q.amax(3)
    owner = torch.arange(P) // M
    exact = []
    for s0 in range(0, P, 500):
        d2 = ((flat[:, s0:s0 + 500, None, :] - flat[:, None, :, :]) ** 2).sum(-1)
        d2[:, owner[s0:s0 + 500, None] == owner[None, :]] = float("inf")
        exact.append(d2.min(-1).values)
    exact = torch.cat(exact, 1).view(B, N, QT, BQ)
    other = torch.arange(N)[:, None] != torch.arange(N)[None, :]
    gaps = box_gap2(qlo[:, :, :, None, None], qhi[:, :, :, None, None], tlo[:, None, None], thi[:, None, None])
    fewest = ((gaps <= exact.amax(-1)[..., None, None]) & other[None, :, None, :, None]).sum((-1, -2)).float()

    def tile_d2(J, kt):  # (B, N, QT, BQ): each query's nearest in tile kt of object J (both (B, N, QT))
        ki = (J * M + kt * BK)[..., None] + torch.arange(BK)
        keys = flat.gather(1, ki.reshape(B, -1, 1).expand(B, ki[0].numel(), 3)).view(B, N, QT, BK, 3)
        return ((q[:, :, :, :, None, :] - keys[:, :, :, None, :, :]) ** 2).sum(-1).min(-1).values

    best = torch.full((B, N, QT, BQ), float("inf"))
    if first == "stride":
        keys = torch.arange(0, P, S)
        for o in range(N):
            d2 = ((q[:, o, :, :, None, :] - flat[:, None, None, keys]) ** 2).sum(-1)
            d2[..., owner[keys] == o] = float("inf")
            best[:, o] = d2.min(-1).values
        pass1 = -(-len(keys) // BK)
    else:
        centre_q = (qlo + qhi) / 2
        centre_t = ((tlo + thi) / 2).view(B, N * KT, 3)
        cd = ((centre_q[:, :, :, None] - centre_t[:, None, None]) ** 2).sum(-1)
        cd = cd.masked_fill(~other.repeat_interleave(KT, 1)[None, :, None, :], float("inf"))
        pick = cd.argmin(-1)
        best = tile_d2(pick // KT, pick % KT)
        pass1 = 1
    visits = torch.zeros(B, N, QT)
    worst = best.amax(-1)
    for j in range(N):
        J = torch.full((B, N, QT), j)
        gap_j = gaps[:, :, :, j]
        go = other[:, j][None, :, None] & (gap_j.amin(-1) <= worst * (1 + slack))
        for kt in range(KT):
            v = go & (gap_j[..., kt] <= worst * (1 + slack))
            if v.any():
                visits += v
                best = torch.where(v[..., None], torch.minimum(best, tile_d2(J, torch.full_like(J, kt))), best)
                worst = best.amax(-1)
    assert torch.allclose(best, exact, rtol=1e-4, atol=1e-7), "the simulated search is not exact"
    return {"first pass": float(pass1), "pass 2": visits.mean().item(), "total": pass1 + visits.mean().item(),
            "fewest pass 2": fewest.mean().item()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rooms", type=int, default=2)
    ap.add_argument("--objects", type=int, default=20)
    ap.add_argument("--points", type=int, default=1984, help="per object, a multiple of 64")
    args = ap.parse_args()
    torch.set_num_threads(1)
    from bench_gpu import BOUNDS, synthetic_batch

    from spread.model.nearest_dense import pose_torch
    from spread.model.poses import denormalize_affine

    batch = synthetic_batch(args.rooms, args.objects, args.points)
    offset, scale = denormalize_affine(torch.tensor(BOUNDS))
    noise = torch.randn(args.rooms, args.objects, 9, generator=torch.Generator().manual_seed(1))
    rows = []
    for poses, states in (("rest", batch["x"]), ("noise", noise)):
        world = pose_torch(states, offset, scale, batch["points"], batch["normals"])[0]
        for first in ("stride", "neartile"):
            r = simulate(world, first)
            rows.append(f"| {poses} | {first} | {r['first pass']:.0f} | {r['pass 2']:.1f} | {r['total']:.1f} | "
                        f"{r['fewest pass 2']:.1f} |")
            print(rows[-1], flush=True)
    print(f"\ntiles of 64 × 64 distances per program, {args.rooms} rooms × {args.objects} objects × {args.points} points")
    print("| poses | first pass | first-pass tiles | pass-2 tiles | total | fewest pass 2 |\n|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
