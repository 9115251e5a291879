"""Quality after a fixed CPU budget: the tiny `geometry` model trained for N minutes, sampled with
DDIM-50 on test graphs, against two floors — random placement and the ground truth.

    python benchmarks/quality_budget.py DATASET --minutes 30 --graphs 100 [--test-dataset DIR] [--threads 1]

Trains on DATASET/train (its stats.json normalises); test graphs come from DATASET/test or from the
test split of ``--test-dataset`` (a dataset generated with another seed from the same asset library).

Random placement: each object keeps its ground-truth rest orientation up to a uniform random yaw,
its xz centre uniform over the room's floor rectangle, its bottom resting on the floor (y such that
the lowest point is at 0) — a layout that ignores the graph. Metrics are the evaluation suite's
per-scene functions (GRecall, Col_mesh, ASD), pooled over all graphs. Prints one table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def random_placement(scene, library, rng):
    from spread.procgen.placement import yaw_matrix

    T = np.empty_like(scene.translation, dtype=np.float64)
    R = np.empty_like(scene.rotation, dtype=np.float64)
    lo, hi = scene.room[0], scene.room[1]
    for i, aid in enumerate(scene.asset_id):
        R[i] = yaw_matrix(rng.uniform(0, 2 * np.pi)) @ scene.rotation[i]
        v = np.asarray(library.mesh(str(aid)).convex_hull.vertices) @ R[i].T
        T[i] = [rng.uniform(lo[0], hi[0]), -v[:, 1].min(), rng.uniform(lo[2], hi[2])]
    return scene.with_poses(T, R, scene_id=scene.scene_id + "_random")


def measure(scenes, library) -> dict:
    from spread.metrics import scene_collisions, scene_graph_recall, scene_support_distance

    matches = pairs = colliding = objects = 0
    asd = []
    for s in scenes:
        g = scene_graph_recall(s, library)
        matches += g.matches
        pairs += g.pairs
        c = scene_collisions(s, library)
        colliding += int(np.sum(c.colliding))
        objects += s.num_objects
        d = scene_support_distance(s, library)
        asd.extend(abs(p.min_signed_distance) for p in d.pairs)
    return {"grecall": matches / max(pairs, 1), "col_mesh": colliding / max(objects, 1),
            "asd": float(np.mean(asd)) if asd else float("nan"), "scenes": len(scenes)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--minutes", type=float, default=30.0)
    ap.add_argument("--graphs", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--out", default="/tmp/quality_budget")
    ap.add_argument("--test-dataset", default=None)
    args = ap.parse_args()

    import lightning as L
    import torch

    from spread.assets import AssetLibrary
    from spread.data import SceneDataModule, collate_scenes
    from spread.model import SceneDiffusion
    from spread.scene import write_scene

    torch.set_num_threads(args.threads)
    root = Path(args.dataset)
    out = Path(args.out)
    library = AssetLibrary.load(root / "assets")
    from spread.configs import model_config

    model_cfg = model_config("tiny")
    dm = SceneDataModule(root, batch_size=args.batch, num_workers=1, num_points=256, seed=0)
    model = SceneDiffusion(variant="geometry", config=model_cfg, sample_every_n_epochs=0)
    trainer = L.Trainer(max_time={"minutes": args.minutes}, accelerator="cpu", devices=1, logger=False,
                        enable_checkpointing=False, limit_val_batches=0, enable_progress_bar=False,
                        default_root_dir=str(out))
    t0 = time.perf_counter()
    trainer.fit(model, datamodule=dm)
    train_s = time.perf_counter() - t0
    steps = trainer.global_step
    model.eval()

    from spread.data import SceneDataset

    test = SceneDataset(Path(args.test_dataset) if args.test_dataset else root, "test", library=library,
                        num_points=256, seed=0)
    n = min(args.graphs, len(test))
    truth = [test.read(i) for i in range(n)]
    generated = []
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(0)
    for start in range(0, n, args.batch):
        items = [test[i] for i in range(start, min(n, start + args.batch))]
        batch = collate_scenes(items)
        with torch.no_grad():
            poses = model.sample(batch, "ddim-50", gen)
        for b, i in enumerate(range(start, start + len(items))):
            k = truth[i].num_objects
            s = truth[i].with_poses(poses.translation[b, :k].numpy(), poses.rotation[b, :k].numpy(),
                                    scene_id=truth[i].scene_id + "_gen")
            generated.append(s)
            write_scene(s, out / "scenes" / f"{s.scene_id}.npz")
    sample_s = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    random = [random_placement(s, library, rng) for s in truth]
    rows = {"ground truth": measure(truth, library), "tiny geometry, DDIM-50": measure(generated, library),
            "random placement": measure(random, library)}
    print(f"# quality_budget {time.strftime('%Y-%m-%d')} dataset={root} train={train_s / 60:.1f} min "
          f"({steps} steps, batch {args.batch}, {args.threads} thread) sampling={sample_s:.0f} s for {n} graphs")
    print("| poses | GRecall ↑ | Col_mesh ↓ | ASD (m) ↓ | scenes |")
    print("|---|---|---|---|---|")
    for name, r in rows.items():
        print(f"| {name} | {r['grecall']:.3f} | {r['col_mesh']:.3f} | {r['asd']:.4f} | {r['scenes']} |")
    (out / "quality.json").write_text(json.dumps({"rows": rows, "train_s": train_s, "steps": steps,
                                                  "sample_s": sample_s}, indent=2))


if __name__ == "__main__":
    main()
