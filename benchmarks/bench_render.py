"""What the pictures cost: seconds per scene of each 3D render and figure, on the rooms of a dataset folder.

    python benchmarks/bench_render.py --data DIR [--split test] [--scenes 8]

Rows: the top-down render (the FID protocol's, for comparison), the 3D view (pybullet TinyRenderer) at
640 × 480 with 2× supersampling (the figures' default) and without, the scene card (3D view + relation
matrix, what ``spread-sample`` writes as ``<name>_3d.png`` and ``spread-ablate`` per row), and before | after
physics (one Stability run + two 3D views, ``<name>_physics.png``). The first scene of each row is a warm-up
(visual shapes are built once per asset and process) and is left out. Prints one table.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", required=True, help="dataset folder (assets/ and the split)")
    parser.add_argument("--split", default="test")
    parser.add_argument("--scenes", type=int, default=8)
    args = parser.parse_args()

    from spread.assets.library import AssetLibrary
    from spread.render import (
        PerspectiveSettings, before_after_figure, render_perspective, render_topdown, scene_card_figure,
    )
    from spread.scene import list_scene_files, read_scene

    library = AssetLibrary.load(Path(args.data) / "assets")
    scenes = [read_scene(p, assets=library) for p in list_scene_files(Path(args.data) / args.split)[:args.scenes + 1]]
    plain = PerspectiveSettings(supersample=1)
    rows = {
        "top-down 256² (FID render)": lambda s: render_topdown(s, library),
        "3D view 640×480, supersample 1": lambda s: render_perspective(s, library, plain),
        "3D view 640×480, supersample 2": lambda s: render_perspective(s, library),
        "scene card (3D + relation matrix)": lambda s: scene_card_figure(s, library),
        "before / after physics (1 run + 2 views)": lambda s: before_after_figure(s, library),
    }
    objects = np.mean([s.num_objects for s in scenes[1:]])
    print(f"{len(scenes) - 1} scenes of {args.data}/{args.split}, {objects:.1f} objects on average\n")
    print("| picture | s per scene (mean) | min | max |")
    print("|---|---:|---:|---:|")
    for name, fn in rows.items():
        seconds = []
        for k, scene in enumerate(scenes):
            t0 = time.perf_counter()
            fn(scene)
            if k:
                seconds.append(time.perf_counter() - t0)
        print(f"| {name} | {np.mean(seconds):.2f} | {np.min(seconds):.2f} | {np.max(seconds):.2f} |")


if __name__ == "__main__":
    main()
