"""Time a fresh build of the full procedural asset library (every category × variants) and its caches.

    python benchmarks/bench_assets.py [--processes 2] [--variants 5] [--seed 0] [--root DIR]

Prints one table: assets built, total seconds, seconds per asset, seconds for the geometry caches,
faces and parts per asset (min / mean / max). Without ``--root`` it builds into a temporary folder.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--variants", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--root", type=Path, default=None, help="library folder (default: a fresh temp folder)")
    args = parser.parse_args()

    t_import = time.perf_counter()
    from spread.assets.build import build_library
    from spread.assets.catalog import default_categories
    t_import = time.perf_counter() - t_import

    with tempfile.TemporaryDirectory() as tmp:
        root = args.root or Path(tmp) / "assets"
        t0 = time.perf_counter()
        lib = build_library(root, variants=args.variants, seed=args.seed, processes=args.processes,
                            progress=False, caches=False)
        t_build = time.perf_counter() - t0
        t0 = time.perf_counter()
        lib.build_caches()
        t_caches = time.perf_counter() - t0

    faces = np.array([lib[a].num_faces for a in lib])
    parts = np.array([lib[a].num_parts for a in lib])
    total = t_build + t_caches
    rows = [
        ("categories", f"{len(default_categories())}"),
        ("assets built", f"{len(lib)}"),
        ("processes", f"{args.processes}"),
        ("seconds total (build + caches)", f"{total:.2f}"),
        ("seconds build", f"{t_build:.2f}"),
        ("seconds per asset", f"{total / len(lib):.4f}"),
        ("seconds for caches", f"{t_caches:.2f}"),
        ("faces min / mean / max", f"{faces.min()} / {faces.mean():.0f} / {faces.max()}"),
        ("parts min / mean / max", f"{parts.min()} / {parts.mean():.1f} / {parts.max()}"),
        ("seconds to import", f"{t_import:.2f}"),
    ]
    width = max(len(k) for k, _ in rows)
    print(f"{'metric':<{width}}  value")
    print(f"{'-' * width}  {'-' * 16}")
    for k, v in rows:
        print(f"{k:<{width}}  {v}")


if __name__ == "__main__":
    main()
