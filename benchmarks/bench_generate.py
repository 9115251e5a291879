"""Room generation throughput: asset library build, first-use caches, rooms per second per core.

    python benchmarks/bench_generate.py [--rooms 40] [--processes 1 2] [--out /tmp/bench_gen]

Prints one table. Rooms are the default generator's (2–52 objects, mean ~20), with physics settling,
repair and the verification re-simulation. Extrapolates to the issue's target (1,000 rooms, 2 cores).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rooms", type=int, default=40)
    ap.add_argument("--processes", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--out", default="/tmp/bench_generate")
    args = ap.parse_args()

    from spread.assets import AssetLibrary
    from spread.assets.build import build_library
    from spread.procgen.dataset import DatasetConfig, generate_dataset

    out = Path(args.out)
    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    build_library(out / "lib", seed=0, processes=max(args.processes), progress=False)
    t_lib = time.perf_counter() - t0
    # caches alone: drop and rebuild them
    shutil.rmtree(out / "lib" / "cache", ignore_errors=True)
    lib = AssetLibrary.load(out / "lib")
    t0 = time.perf_counter()
    lib.build_caches()
    t_cache = time.perf_counter() - t0

    rows = []
    for p in args.processes:
        target = out / f"p{p}"
        shutil.copytree(out / "lib", target / "assets")
        t0 = time.perf_counter()
        manifest = generate_dataset(target, DatasetConfig(rooms=args.rooms, seed=0, processes=p, renders=0),
                                    progress=False)
        wall = time.perf_counter() - t0
        stats = manifest["statistics"]
        rows.append((p, wall, manifest["this_run"]["rooms_generated"], stats["objects_per_room"]["mean"],
                     manifest["this_run"]["mean_attempts"]))

    print(f"# bench_generate  {time.strftime('%Y-%m-%d')}  {platform.processor() or platform.machine()}  "
          f"{len(lib)} assets  rooms={args.rooms}")
    print(f"asset library build (incl. caches): {t_lib:.1f} s   caches alone: {t_cache:.1f} s "
          f"({1000 * t_cache / len(lib):.0f} ms/asset)")
    print("| processes | rooms | mean objects | attempts/room | wall s | rooms/s | rooms/s/core | 1,000 rooms (min) |")
    print("|---|---|---|---|---|---|---|---|")
    for p, wall, n, mean_obj, att in rows:
        rps = n / wall
        print(f"| {p} | {n} | {mean_obj:.1f} | {att:.2f} | {wall:.1f} | {rps:.2f} | {rps / p:.2f} | "
              f"{1000 / rps / 60:.1f} |")
    if len(rows) == 2:
        print(f"speed-up {rows[0][0]}→{rows[1][0]} processes: {rows[0][1] / rows[1][1] * rows[1][2] / max(rows[0][2], 1):.2f}×")
    (out / "result.json").write_text(json.dumps({"library_s": t_lib, "cache_s": t_cache, "rows": rows}))


if __name__ == "__main__":
    main()
