"""The CPU's nearest-other-object point searches on the same posed points, one table: ``pruned`` (torch, blocks of
queries against the boxes' survivors), ``tree`` (scipy k-d trees, :func:`spread.model.nearest.nearest_other_point_tree`)
and, with ``--old REV``, the tree search of another commit, with ``--brute`` brute force in torch (what
``nearest=dense`` ran on the CPU for up to 2²⁸ distances until stop 60; now the trees); seconds a call (best of
``--repeats`` after one warm-up, one thread), and how many indices differ from this commit's tree (ties aside they
should not).

Rooms are bench_gpu's (boxes of 0.2–1.2 m on a 6 m floor, Morton-ordered surface points) at their own poses
(``rest``) and at standard-normal states (``noise``: a training step's x_t at large t, objects overlapping anywhere in
the room's bounds and beyond).

    python benchmarks/bench_tree.py --old 57298c8                 # ~1 minute
    python benchmarks/bench_tree.py --sizes 16x20x256 4x20x2000
    python benchmarks/bench_tree.py --brute --no-pruned --sizes 2x6x64 2x20x64 8x20x64 2x20x256 4x20x256 2x40x256
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).parent))


def old_tree(rev: str):
    """``nearest_other_point_tree`` as commit ``rev`` wrote it (its module loaded beside this one's)."""
    source = subprocess.run(["git", "show", f"{rev}:src/spread/model/nearest.py"], capture_output=True, text=True,
                            check=True, cwd=Path(__file__).parent).stdout
    path = Path(tempfile.mkdtemp()) / "old_nearest.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("old_nearest", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.nearest_other_point_tree


def best_of(fn, args, repeats: int) -> tuple[float, torch.Tensor]:
    out = fn(*args)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*args)
        times.append(time.perf_counter() - t0)
    return min(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", nargs="+", default=["16x20x256", "4x20x1000", "4x20x2000", "4x50x1000"],
                    help="B x N x M: scenes, objects, points per object")
    ap.add_argument("--old", help="a commit whose tree search to time beside this one's")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--no-pruned", action="store_true", help="leave out the (slow) pruned search")
    ap.add_argument("--brute", action="store_true", help="time brute force in torch beside the tree (small sizes)")
    args = ap.parse_args()
    torch.set_num_threads(1)
    from bench_gpu import BOUNDS, synthetic_batch

    from spread.model.nearest import nearest_other_point, nearest_other_point_tree
    from spread.model.nearest_dense import _brute_force
    from spread.model.poses import pose_points, poses_from_state

    previous = old_tree(args.old) if args.old else None
    bounds = torch.tensor(BOUNDS)
    print(f"| B × N × M | poses | pruned s | tree{' ' + args.old if args.old else ''} s | tree s (this) | "
          f"speed-up | indices ≠ |{' brute force s | brute / tree | brute ≠ tree |' if args.brute else ''}\n"
          f"|---|---|---:|---:|---:|---:|---:|{'---:|---:|---:|' if args.brute else ''}")
    for size in args.sizes:
        B, N, M = (int(v) for v in size.split("x"))
        batch = synthetic_batch(B, N, M)
        for poses in ("rest", "noise"):
            x = batch["x"] if poses == "rest" else torch.randn(B, N, 9, generator=torch.Generator().manual_seed(1))
            translation, rotation = poses_from_state(x, bounds)
            world = pose_points(batch["points"], translation, rotation)
            t_new, i_new = best_of(nearest_other_point_tree, (world, batch["mask"]), args.repeats)
            cells, base, differ = [], t_new, 0
            if not args.no_pruned:
                t_p, _ = best_of(nearest_other_point, (world, batch["points"], translation, rotation, batch["mask"]),
                                 1)
                cells.append(f"{t_p:.3f}")
                base = t_p
            else:
                cells.append("–")
            if previous is not None:
                t_old, i_old = best_of(previous, (world, batch["mask"]), args.repeats)
                differ = int((i_old != i_new).sum())
                cells.append(f"{t_old:.3f}")
                base = t_old
            else:
                cells.append("–")
            row = f"| {B} × {N} × {M} | {poses} | {' | '.join(cells)} | {t_new:.3f} | {base / t_new:.2f}× | {differ} |"
            if args.brute:
                flat, valid = world.reshape(B, N * M, 3), batch["mask"].bool().repeat_interleave(M, dim=1)
                t_b, i_b = best_of(_brute_force, (flat, valid, M), 1)
                row += f" {t_b:.4f} | {t_b / t_new:.1f}× | {int(((i_b != i_new) & valid).sum())} |"
            print(row, flush=True)


if __name__ == "__main__":
    main()
