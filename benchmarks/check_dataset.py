"""Ground-truth grade of every room of a dataset folder (spread.procgen.quality), one table.

    python benchmarks/check_dataset.py /tmp/x [--processes 2]

Exact trimesh distances, FCL pairs and a physics re-simulation per room; prints the worst values over
the dataset and the rooms that fail any check.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np

_LIB = {}


def _check(path: str) -> dict:
    from spread.assets import AssetLibrary
    from spread.procgen.quality import check_room
    from spread.scene import read_scene

    root = Path(path).parent.parent
    if "lib" not in _LIB:
        _LIB["lib"] = AssetLibrary.load(root / "assets")
    lib = _LIB["lib"]
    return check_room(read_scene(path, assets=lib), lib).to_dict()


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("root")
    ap.add_argument("--processes", type=int, default=2)
    args = ap.parse_args()
    root = Path(args.root)
    files = sorted(str(p) for s in ("train", "val", "test") for p in (root / s).glob("*.npz"))
    t0 = time.perf_counter()
    with mp.get_context("spawn").Pool(args.processes) as pool:
        results = pool.map(_check, files, chunksize=4)
    wall = time.perf_counter() - t0
    objects = sum(r["num_objects"] for r in results)
    support = np.array([d for r in results for d in r["support_distances"]])
    moved = sum(r["resim_moved"] for r in results)
    failing = [r for r in results if r["failures"]]
    print(f"# check_dataset {root}  {time.strftime('%Y-%m-%d')}  rooms={len(results)} objects={objects}  {wall:.0f} s")
    print("| check | threshold | measured | rooms failing |")
    print("|---|---|---|---|")
    print(f"| deepest pair penetration | < 1 cm | {max(r['max_penetration'] for r in results) * 1000:.2f} mm | "
          f"{sum(r['max_penetration'] >= 0.01 for r in results)} |")
    print(f"| support distance (max / mean over {len(support)} pairs) | < 2 mm | "
          f"{support.max() * 1000:.3f} / {support.mean() * 1000:.3f} mm | "
          f"{sum(r['max_support_distance'] >= 0.002 for r in results)} |")
    print(f"| small objects without exactly one supporter | 0 | "
          f"{sum(len(r['objects_without_one_supporter']) for r in results)} | "
          f"{sum(bool(r['objects_without_one_supporter']) for r in results)} |")
    print(f"| support forest rooted at floor furniture | all | "
          f"{sum(not r['forest_errors'] for r in results)}/{len(results)} rooms | "
          f"{sum(bool(r['forest_errors']) for r in results)} |")
    print(f"| objects still (< 1 cm) after 100 × 1/60 s | ≥ 98% | {100 * (1 - moved / objects):.2f}% | "
          f"{sum(r['resim_still_share'] < 0.98 for r in results)} |")
    for r in failing[:20]:
        print(f"FAIL {r['scene_id']}: {'; '.join(r['failures'])}")


if __name__ == "__main__":
    main()
