"""The nearest-point search kernel of another commit against this one, on the same posed points: the same answer
(indices and signed distances), and each one's CUDA time, the new one also with ``--block-q`` queries a program (median of 5 after 2). Needs a GPU for times; on a CPU with
``TRITON_INTERPRET=1`` it checks the answers at a toy size.

    git show bd5cb3d:src/spread/model/nearest_dense.py | sed 's/spread::/spreadold::/g' > .gpudata/old_nearest_dense.py
    python benchmarks/search_ab.py --old .gpudata/old_nearest_dense.py [--json out.json]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))


def timed(op, args) -> tuple[float, tuple]:
    """Median CUDA ms of ``op(*args)`` over 5 calls after 2, and the last result (without CUDA: 0 ms, one call)."""
    if not torch.cuda.is_available():
        return 0.0, op(*args)
    for _ in range(2):
        result = op(*args)
    torch.cuda.synchronize()
    times = []
    for _ in range(5):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        result = op(*args)
        end.record()
        torch.cuda.synchronize()
        times.append(start.elapsed_time(end))
    return sorted(times)[2], result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", type=Path, required=True, help="the other commit's nearest_dense.py, ops renamed spreadold::")
    ap.add_argument("--block-q", type=int, default=32, help="also time the new kernel with this many queries a program")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from bench_gpu import BOUNDS, synthetic_batch

    import spread.model.nearest_dense as new
    from spread.model.poses import denormalize_affine

    spec = importlib.util.spec_from_file_location("old_nearest_dense", args.old)
    spec.loader.exec_module(importlib.util.module_from_spec(spec))
    dev = "cuda" if torch.cuda.is_available() else "cpu"
    offset, scale = denormalize_affine(torch.tensor(BOUNDS, device=dev))
    sizes = [(16, 20, 2000), (64, 20, 2000), (64, 40, 2000)] if dev == "cuda" else [(2, 5, 300)]
    out, rows = {}, []
    for B, N, M in sizes:
        batch = synthetic_batch(B, N, M, device=dev)
        for poses in ("rest", "noise"):
            x = batch["x"] if poses == "rest" else torch.randn(B, N, 9, generator=torch.Generator().manual_seed(1)).to(dev)
            world, normals, boxes = torch.ops.spread.pose_states(x, offset, scale, batch["points"], batch["normals"],
                                                                 new.BLOCK_K)
            inputs = (world, normals, boxes, batch["mask"], 10.0)
            t_old, (i_old, d_old) = timed(torch.ops.spreadold.signed_nearest, inputs)
            t_new, (i_new, d_new) = timed(torch.ops.spread.signed_nearest, inputs)
            new.BLOCK_Q, default_q = args.block_q, new.BLOCK_Q  # the same kernel with other query tiles
            try:
                t_q, (i_q, d_q) = timed(torch.ops.spread.signed_nearest, inputs)
            finally:
                new.BLOCK_Q = default_q
            key = f"search/B{B}_N{N}_M{M}/{poses}"
            out[key] = {"old_ms": round(t_old, 3), "new_ms": round(t_new, 3), f"new_q{args.block_q}_ms": round(t_q, 3),
                        "indices_differ": int((i_old != i_new).sum() + (i_q != i_new).sum()),
                        "max_distance_diff": float(torch.maximum((d_old - d_new).abs().max(), (d_q - d_new).abs().max()))}
            rows.append(f"| {B} × {N} × {M} | {poses} | {t_old:.2f} | {t_new:.2f} | {t_q:.2f} | "
                        f"{out[key]['indices_differ']} | {out[key]['max_distance_diff']:.1e} |")
    where = "cpu, Triton's interpreter" if os.environ.get("TRITON_INTERPRET") == "1" else "cpu, the torch paths"
    print(f"device: {torch.cuda.get_device_name() if dev == 'cuda' else where}; kernels fell back: "
          f"{sorted(new._BROKEN) or 'none'}")
    print(f"| B × N × M | poses | old ms | new ms | new, BLOCK_Q {args.block_q} ms | indices that differ | "
          "max distance diff |\n|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
