"""The nearest-point search kernel at other tile sizes: queries a program (BLOCK_Q), keys a tile (BLOCK_K, and the boxes
made for it), warps a program (NUM_WARPS), and how it keeps each query's nearest (PACKED_KEYS: one int64 key, or d²
and the index apart) — each one's CUDA time on the same posed points, and that each gives
the default's answer (indices and signed distances). Then, on any machine, the distances each choice computes,
replayed on the CPU (``search_tiles.simulate``: the kernel's culling decisions, exact), so a GPU's times can be read
beside the arithmetic they did.

Why: the search is ~30 % of a +Geometry denoising step on an H200 (RESULTS.md, fifth slot); BLOCK_Q 64 → 32 made it
1.7–1.8× faster (fourth slot) where the replay counted only 1.2× fewer distances, and the replay counts 1.58× fewer
again at 16 × 32 (RESULTS.md, stop 59). Any choice is exact; only a GPU can say which is fastest.

    python benchmarks/search_blocks.py [--json OUT.json]          # a GPU: 16 and 64 rooms × 20 objects × 2,000 points
    TRITON_INTERPRET=1 python benchmarks/search_blocks.py         # CPU: the kernels' answers at a toy size
    python benchmarks/search_blocks.py --replay --points 1024     # CPU: distances per query of each choice (~6 min)
    python benchmarks/search_blocks.py --registers [90]           # CPU: each choice compiled for sm_90, its registers
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))

#: (BLOCK_Q, BLOCK_K, NUM_WARPS, PACKED_KEYS): the default first; the last, 64 queries, the default before the
#: fourth slot (1.7–1.8× slower there), as a check that this run's times agree with that slot's.
CHOICES = [(32, 64, 4, True), (32, 64, 8, True), (16, 64, 4, True), (16, 64, 8, True), (16, 32, 2, True),
           (16, 32, 4, True), (32, 32, 2, True), (8, 64, 2, True), (16, 16, 2, True), (32, 64, 4, False),
           (16, 32, 4, False), (64, 64, 4, True)]


#: The search kernel's arguments as Triton types, for compiling it without a GPU (:func:`compiled`).
SEARCH_SIGNATURE = {"pts_ptr": "*fp32", "nrm_ptr": "*fp32", "box_ptr": "*fp32", "valid_ptr": "*i8", "idx_ptr": "*i64",
                    "dist_ptr": "*fp32", "N": "i32", "M": "i32", "KT": "i32", "QT": "i32", "NO_NEIGHBOUR": "fp32",
                    "BQ": "constexpr", "BK": "constexpr", "SLACK": "constexpr", "KTP": "constexpr",
                    "PACKED": "constexpr"}


def compiled(choice: tuple[int, int, int, bool], arch: int = 90, points: int = 2000) -> dict:
    """The search kernel at ``choice`` compiled for CUDA compute capability ``arch`` (90: H100/H200) without a GPU —
    Triton's compiler and its bundled ``ptxas`` — and what the machine code needs per thread: ``registers``,
    ``stack`` and ``local`` (spilled) bytes, as ``cuobjdump --dump-resource-usage`` reads them from the cubin, and
    ``warps_per_sm`` (of 64) that many registers leave room for (65,536 a multiprocessor, whole programs)."""
    import re
    import subprocess
    import tempfile

    import triton
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    import spread.model.nearest_dense as nd

    bq, bk, warps, packed = choice
    kernels = nd._triton_kernels()
    if kernels is None:
        raise RuntimeError("search_blocks: Triton is not importable here")
    constexprs = {"BQ": bq, "BK": bk, "SLACK": nd.CULL_SLACK, "KTP": triton.next_power_of_2(-(-points // bk)),
                  "PACKED": packed}
    kernel = triton.compile(ASTSource(fn=kernels[2], signature=SEARCH_SIGNATURE, constexprs=constexprs),
                            target=GPUTarget("cuda", arch, 32), options={"num_warps": warps})
    tool = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "cuobjdump"
    with tempfile.TemporaryDirectory() as tmp:
        cubin = Path(tmp) / "search.cubin"
        cubin.write_bytes(kernel.asm["cubin"])
        usage = subprocess.run([str(tool), "--dump-resource-usage", str(cubin)], capture_output=True, text=True,
                               check=True).stdout
    found = {k.lower(): int(v) for k, v in re.findall(r"\b(REG|STACK|LOCAL):(\d+)", usage)}
    registers = found["reg"]
    per_warp = -(-registers // 8) * 8 * 32  # registers are given out per warp, 8 a thread at a time
    blocks = min(32, 65536 // (per_warp * warps))  # blocks a multiprocessor holds by registers alone
    return {"registers": registers, "stack": found.get("stack", 0), "local": found.get("local", 0),
            "warps_per_sm": min(64, blocks * warps)}


def kernel_rows(choices: list[tuple[int, int, int, bool]], save=lambda out: None) -> tuple[dict, list[str]]:
    """Each choice's time and answer against the default's, ``save(out)`` after each (a slot cut short keeps them); a
    choice Triton cannot build is marked as fallen back (the torch path answered it) and the next gets its own try."""
    from bench_gpu import BOUNDS, synthetic_batch
    from search_ab import timed

    import spread.model.nearest_dense as nd
    from spread.model.poses import denormalize_affine

    dev = "cuda" if torch.cuda.is_available() else "cpu"
    offset, scale = denormalize_affine(torch.tensor(BOUNDS, device=dev))
    sizes = [(16, 20, 2000), (64, 20, 2000)] if dev == "cuda" else [(2, 5, 150)]
    default = (nd.BLOCK_Q, nd.BLOCK_K, nd.NUM_WARPS, nd.PACKED_KEYS)
    out, rows, failed = {}, [], set()
    for B, N, M in sizes:
        batch = synthetic_batch(B, N, M, device=dev)
        for poses in ("rest", "noise"):
            noise = torch.randn(B, N, 9, generator=torch.Generator().manual_seed(1)).to(dev)
            x = batch["x"] if poses == "rest" else noise
            world, normals, _ = nd.pose_torch(x, offset, scale, batch["points"], batch["normals"])
            reference = None
            for bq, bk, warps, packed in choices:
                nd.BLOCK_Q, nd.BLOCK_K, nd.NUM_WARPS, nd.PACKED_KEYS = bq, bk, warps, packed
                try:
                    boxes = nd.tile_boxes(world, bk)
                    ms, (index, distance) = timed(torch.ops.spread.signed_nearest,
                                                  (world, normals, boxes, batch["mask"], 10.0))
                finally:
                    nd.BLOCK_Q, nd.BLOCK_K, nd.NUM_WARPS, nd.PACKED_KEYS = default
                fell_back = "search" in nd._BROKEN  # Triton failed this choice: the torch path answered, not timed
                if fell_back:
                    failed.add((bq, bk, warps, packed))
                    nd._BROKEN.discard("search")  # the next choice gets its own try
                if reference is None:
                    reference = (index, distance, ms)
                differ = int((index != reference[0]).sum())
                diff = float((distance - reference[1]).abs().max())
                key = f"search/B{B}_N{N}_M{M}/{poses}/q{bq}_k{bk}_w{warps}_{'packed' if packed else 'apart'}"
                out[key] = {"ms": round(ms, 3), "indices_differ": differ, "max_distance_diff": diff,
                            "fell_back": fell_back}
                speed = f"{reference[2] / ms:.2f}×" if ms and not fell_back else "–"
                kept = "packed" if packed else "apart"
                time_text = "fell back" if fell_back else f"{ms:.2f}"
                rows.append(f"| {B} × {N} × {M} | {poses} | {bq} | {bk} | {warps} | {kept} | {time_text} | {speed} | "
                            f"{differ} | {diff:.1e} |")
                save(out)
            print(f"  {B} × {N} × {M}, {poses}: {len(choices)} choices timed", flush=True)
    out["broken"] = [f"q{bq}_k{bk}_w{w}_{'packed' if p else 'apart'}" for bq, bk, w, p in sorted(failed)]
    return out, rows


def replay_rows(choices: list[tuple[int, int, int, bool]], rooms: int, objects: int,
                points: int) -> tuple[dict, list[str]]:
    """Distances per query each (BLOCK_Q, BLOCK_K) computes, the kernel's decisions replayed (warps and keys do not
    change them)."""
    from bench_gpu import BOUNDS, synthetic_batch
    from search_tiles import simulate

    from spread.model.nearest_dense import pose_torch
    from spread.model.poses import denormalize_affine

    batch = synthetic_batch(rooms, objects, points)
    offset, scale = denormalize_affine(torch.tensor(BOUNDS))
    noise = torch.randn(rooms, objects, 9, generator=torch.Generator().manual_seed(1))
    out, rows = {}, []
    blocks = list(dict.fromkeys((bq, bk) for bq, bk, _, _ in choices))
    for poses, states in (("rest", batch["x"]), ("noise", noise)):
        world = pose_torch(states, offset, scale, batch["points"], batch["normals"])[0]
        for bq, bk in blocks:
            r = simulate(world, "neartile", BQ=bq, BK=bk)
            per_query = r["total"] * bk
            out[f"replay/{poses}/q{bq}_k{bk}"] = {"tiles_per_program": round(r["total"], 2),
                                                  "fewest": round(r["fewest pass 2"], 2),
                                                  "distances_per_query": round(per_query)}
            rows.append(f"| {poses} | {bq} | {bk} | {r['total']:.1f} | {r['fewest pass 2']:.1f} | {per_query:.0f} |")
            print(rows[-1], flush=True)
    return out, rows


def register_rows(choices: list[tuple[int, int, int, bool]], arch: int) -> tuple[dict, list[str]]:
    """:func:`compiled` for every choice (no GPU needed)."""
    out, rows = {}, []
    for choice in choices:
        bq, bk, warps, packed = choice
        r = compiled(choice, arch)
        out[f"compiled/sm{arch}/q{bq}_k{bk}_w{warps}_{'packed' if packed else 'apart'}"] = r
        rows.append(f"| {bq} | {bk} | {warps} | {'packed' if packed else 'apart'} | {r['registers']} | {r['stack']} | "
                    f"{r['local']} | {r['warps_per_sm']} |")
    return out, rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--replay", action="store_true", help="the CPU replay of the distances each choice computes")
    ap.add_argument("--registers", type=int, metavar="ARCH", nargs="?", const=90, default=None,
                    help="compile each choice for CUDA compute capability ARCH (90: H100/H200) here, no GPU needed, "
                         "and print its registers, stack and spills")
    ap.add_argument("--rooms", type=int, default=2, help="--replay: rooms of synthetic boxes")
    ap.add_argument("--objects", type=int, default=20)
    ap.add_argument("--points", type=int, default=1024, help="--replay: per object, a multiple of 64")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    torch.set_num_threads(int(os.environ.get("THREADS", "1")) if not torch.cuda.is_available() else 8)
    if args.registers is not None:
        out, rows = register_rows(CHOICES, args.registers)
        print(f"the search kernel compiled for sm_{args.registers} (Triton's compiler and ptxas, no GPU)")
        head = ("| BLOCK_Q | BLOCK_K | warps | nearest kept | registers a thread | stack bytes | spilled bytes | "
                "warps a multiprocessor holds |\n|---|---|---|---|---|---|---|---|")
    elif args.replay:
        out, rows = replay_rows(CHOICES, args.rooms, args.objects, args.points)
        head = ("| poses | BLOCK_Q | BLOCK_K | tiles a program | fewest any order | distances a query |\n"
                "|---|---|---|---|---|---|")
        print(f"\nthe kernel's decisions replayed: {args.rooms} rooms × {args.objects} objects × {args.points} "
              "points")
    else:
        out, rows = kernel_rows(CHOICES, lambda out: args.json and args.json.write_text(json.dumps(out, indent=1)))
        where = torch.cuda.get_device_name() if torch.cuda.is_available() else (
            "cpu, Triton's interpreter" if os.environ.get("TRITON_INTERPRET") == "1" else "cpu, the torch paths")
        head = ("| B × N × M | poses | BLOCK_Q | BLOCK_K | warps | nearest kept | ms | vs default | "
                "indices that differ | max distance diff |\n|---|---|---|---|---|---|---|---|---|---|")
        rows.append(f"device: {where}; kernels fell back: {out['broken'] or 'none'}")
    print(head)
    print("\n".join(rows))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
