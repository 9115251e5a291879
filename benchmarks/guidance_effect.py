"""What the guidance operator does on its own: jittered ground-truth rooms, refined with guidance steps only
(no network), scored with the evaluation's Col_mesh, ASD and GRecall, for weights = k × the paper's λ.

    python benchmarks/guidance_effect.py DATASET [--sigma 0.05] [--scales 0,1,10,100] [--iterations 100]

Each test scene's translations get N(0, sigma²) per axis (benchmarks/jitter_scenes.py, seeded), then
``iterations`` guidance steps (x ← x − Σ kλ ∇G, gravity in the later half, the release's refine loop
without its t = 0 network projection) on the normalised states of the dataset's stats.json. Prints one
table: weights scale, Col_mesh, ASD (mm), GRecall, guidance seconds per scene. Independent of any model:
it says how far the paper's weights move objects per step on our rooms.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from jitter_scenes import jitter_scene  # noqa: E402


def main() -> None:
    from spread.data import SceneDataset, collate_scenes
    from spread.data.stats import load_stats
    from spread.guidance import GuidanceConfig, SceneGuidance
    from spread.metrics import scene_collisions, scene_graph_recall, scene_support_distance
    from spread.model.poses import poses_from_state

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dataset", type=Path)
    ap.add_argument("--split", default="test")
    ap.add_argument("--sigma", type=float, default=0.05, help="jitter per axis, metres")
    ap.add_argument("--scales", default="0,1,10,100", help="multiples of the paper's weights")
    ap.add_argument("--iterations", type=int, default=100)
    ap.add_argument("--scenes", type=int, default=20)
    args = ap.parse_args()
    torch.set_num_threads(1)

    data = SceneDataset(args.dataset, args.split)
    bounds = torch.tensor(load_stats(args.dataset / "stats.json")["bounds_translations"], dtype=torch.float32)
    scenes = [jitter_scene(data.read(k), args.sigma, np.random.default_rng([0, k]))
              for k in range(min(args.scenes, len(data)))]
    batch = collate_scenes([data.encode(s) for s in scenes])
    print(f"{len(scenes)} scenes of {args.dataset / args.split}, jitter {args.sigma * 1000:.0f} mm, "
          f"{args.iterations} guidance iterations")
    print(f"{'scale':>6} {'Col_mesh':>9} {'ASD mm':>8} {'GRecall':>8} {'s/scene':>8}")
    for scale in [float(s) for s in args.scales.split(",")]:
        cfg = GuidanceConfig(mode="refine", collision=7.5e-3 * scale, gravity=1e-3 * scale, relation=1e-3 * scale,
                             iterations=args.iterations, denoise_every=0)
        x = batch["x"].clone()
        started = time.perf_counter()
        if cfg.active:
            guidance = SceneGuidance(cfg, data.library, [list(s.asset_id) for s in scenes], batch["physical"],
                                     batch["mask"], bounds)
            first_gravity = math.ceil(cfg.gravity_from * cfg.iterations)
            for it in range(cfg.iterations):
                x = guidance.step(x, gravity=it >= first_gravity)
        seconds = (time.perf_counter() - started) / len(scenes)
        t, R = poses_from_state(x, bounds)
        colliding = objects = 0
        asd, correct, pairs = [], 0, 0
        for b, s in enumerate(scenes):
            n = s.num_objects
            Rb = R[b, :n].double().numpy()
            U, _, Vt = np.linalg.svd(Rb)
            out = s.with_poses(t[b, :n].numpy().astype(np.float32), (U @ Vt).astype(np.float32))
            col = scene_collisions(out, data.library)
            colliding += sum(col.colliding)
            objects += n
            asd += [abs(p.min_signed_distance) for p in scene_support_distance(out, data.library).pairs]
            gr = scene_graph_recall(out, data.library)
            correct, pairs = correct + gr.matches, pairs + gr.pairs
        print(f"{scale:6g} {colliding / objects:9.3f} {1000 * np.mean(asd):8.1f} {correct / max(pairs, 1):8.3f} "
              f"{seconds:8.2f}")


if __name__ == "__main__":
    main()
