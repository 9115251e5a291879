"""Evaluation metrics cost: seconds per room for each metric, and the total for 100 rooms without FID.

    python benchmarks/bench_metrics.py [--rooms 100] [--dataset DIR] [--perturb 0.01] [--out /tmp/bench_metrics]

Rooms: the test/val/train scenes of ``--dataset`` (a dataset folder), else a fresh
``spread.procgen.dataset.generate_dataset`` under ``--out``, else (when the generator is not usable)
synthetic rooms of 20 box-built objects (6 pieces of furniture, some with legs, and 14 objects on
their tops, some stacked). Poses get Gaussian noise of ``--perturb`` metres (positions) so that rooms look
like model output, with collisions, floating objects and things that fall: settled rooms would flatter
Col_mesh and Stability. One process, caches cold at the first room (as in a fresh evaluation worker).
FID is timed as render + a tiny injected extractor (clean-fid's weights are not on this machine).
Prints one table.
"""

from __future__ import annotations

import argparse
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def dataset_rooms(root: Path, count: int):
    from spread.assets import AssetLibrary
    from spread.scene import list_scene_files, read_scene

    library = AssetLibrary.load(root / "assets")
    files = [f for split in ("test", "val", "train") if (root / split).is_dir() for f in list_scene_files(root / split)]
    return library, [read_scene(f, assets=library) for f in files[:count]]


def generated_rooms(out: Path, count: int):
    from spread.procgen.dataset import DatasetConfig, generate_dataset

    generate_dataset(out, DatasetConfig(rooms=count, seed=0, processes=2, renders=0), progress=False)
    return dataset_rooms(out, count)


FURNITURE = {"table": (1.2, 0.75, 0.8), "desk": (1.0, 0.72, 0.6), "shelf": (0.8, 1.2, 0.35),
             "nightstand": (0.5, 0.55, 0.4), "tv_stand": (1.4, 0.5, 0.45), "coffee_table": (0.9, 0.4, 0.6)}
OBJECTS = {"book": (0.2, 0.04, 0.3), "mug": (0.09, 0.1, 0.09), "box": (0.3, 0.2, 0.25),
           "bowl": (0.16, 0.07, 0.16), "lamp": (0.15, 0.4, 0.15), "laptop": (0.34, 0.02, 0.24)}


def legged(name, size):
    """A table-like asset: a top board on four legs (a non-convex watertight union)."""
    from spread.assets.assemble import AssetSpec, box_part

    w, h, d = size
    top, leg = 0.04, 0.05
    parts = [box_part((w, top, d), (0, h - top / 2, 0))]
    parts += [box_part((leg, h - top + 0.001, leg), (sx * (w - leg) / 2, (h - top) / 2, sz * (d - leg) / 2))
              for sx in (-1, 1) for sz in (-1, 1)]
    return AssetSpec(name, name, 0, "furniture", parts, density=600.0)


def synthetic_rooms(out: Path, count: int, seed: int = 0):
    """Rooms of 6 furniture boxes on the floor and 14 objects on their tops (module docstring)."""
    from spread.assets.assemble import box_asset, library_from_specs
    from spread.relations import scene_spatial_codes
    from spread.scene import Scene

    specs = [legged(n, s) if n in ("table", "desk", "coffee_table") else box_asset(n, s, category=n, role="furniture")
             for n, s in FURNITURE.items()]
    specs += [box_asset(n, s, category=n) for n, s in OBJECTS.items()]
    library = library_from_specs(out / "assets", specs)
    rng = np.random.default_rng(seed)
    rooms = []
    for k in range(count):
        ids, T, parent = [], [], []
        for name in rng.choice(list(FURNITURE), 6):  # furniture on a 3 × 2 grid of 1.6 m cells
            cell = len(ids)
            ids.append(str(name))
            T.append([(cell % 3) * 1.6 + rng.uniform(-0.2, 0.2), FURNITURE[name][1] / 2,
                      (cell // 3) * 1.6 + rng.uniform(-0.2, 0.2)])
            parent.append(-1)
        tops = {i: [FURNITURE[ids[i]][1], 0] for i in range(6)}  # furniture index → [top height, objects on it]
        for name in rng.choice(list(OBJECTS), 14):
            if rng.random() < 0.2 and len(ids) > 6 and ids[-1] in ("book", "box"):
                base = len(ids) - 1  # stack on the last object
                y = T[base][1] + OBJECTS[ids[base]][1] / 2
                x, z = T[base][0], T[base][2]
            else:
                base = int(rng.integers(6))
                fw, _, fd = FURNITURE[ids[base]]
                slot = tops[base][1]
                tops[base][1] += 1
                x = T[base][0] - fw / 2 + (0.15 + 0.3 * slot) % fw
                z = T[base][2] + rng.uniform(-fd / 4, fd / 4)
                y = tops[base][0]
            ids.append(str(name))
            T.append([x, y + OBJECTS[name][1] / 2, z])
            parent.append(base)
        n = len(ids)
        T = np.array(T, np.float32)
        R = np.tile(np.eye(3, dtype=np.float32), (n, 1, 1))
        physical = np.zeros((n, n), np.int8)
        for j, i in enumerate(parent):
            if i >= 0:
                physical[i, j] = 1
        spatial = scene_spatial_codes(T, R, ids, library)
        rooms.append(Scene(f"bench_{k:04d}", np.array(ids), np.array([library[a].category for a in ids]), T, R,
                           spatial, physical, room=np.array([[-1, 0, -1], [4.2, 3, 2.6]], np.float32)))
    return library, rooms


def perturb(scenes, sigma: float, seed: int = 0):
    """Gaussian position noise (metres), keeping each scene's graphs: stand-ins for generated scenes."""
    rng = np.random.default_rng(seed)
    out = []
    for s in scenes:
        t = s.translation + rng.normal(0, sigma, s.translation.shape).astype(np.float32)
        t[:, 1] = np.maximum(t[:, 1], s.translation[:, 1] - 2 * sigma)
        out.append(s.with_poses(t, s.rotation))
    return out


class TinyFeatures:
    """A stand-in FID extractor (per-channel mean and spread): times the render side of FID."""

    feature_dim = 6

    def __call__(self, images):
        x = np.asarray(images, np.float64).reshape(len(images), -1, 3)
        return np.concatenate([x.mean(1), x.std(1)], 1)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rooms", type=int, default=100)
    ap.add_argument("--dataset", type=Path, default=None)
    ap.add_argument("--perturb", type=float, default=0.01)
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "bench_metrics",
                    help="scratch folder for generated rooms (emptied first; unused with --dataset)")
    args = ap.parse_args()

    from spread.metrics import (
        fid_render, scene_collisions, scene_graph_recall, scene_stability, scene_support_distance,
    )

    source = "dataset"
    if args.dataset is not None:
        library, rooms = dataset_rooms(args.dataset, args.rooms)
    else:
        shutil.rmtree(args.out, ignore_errors=True)  # generated fresh every time
        args.out.mkdir(parents=True)
        try:
            library, rooms = generated_rooms(args.out / "generated", args.rooms)
            source = "generate_dataset"
        except Exception as exc:  # the generator is another part; fall back rather than fail the benchmark
            library, rooms = synthetic_rooms(args.out, args.rooms)
            source = f"synthetic box rooms (generate_dataset failed: {type(exc).__name__}: {str(exc)[:60]})"
    rooms = perturb(rooms, args.perturb)
    extractor = TinyFeatures()
    metrics = {
        "Col_mesh": lambda s: scene_collisions(s, library),
        "GRecall": lambda s: scene_graph_recall(s, library),
        "ASD": lambda s: scene_support_distance(s, library),
        "Stability (10 x 100 steps)": lambda s: scene_stability(s, library),
        "FID render + tiny extractor": lambda s: extractor(fid_render(s, library)[None]),
    }
    times = {name: [] for name in metrics}
    values = {"Col_mesh": [], "GRecall": [], "ASD": [], "Stability (10 x 100 steps)": []}
    for scene in rooms:
        for name, fn in metrics.items():
            t0 = time.perf_counter()
            result = fn(scene)
            times[name].append(time.perf_counter() - t0)
            if name == "Col_mesh":
                values[name].append(result.rate)
            elif name == "GRecall" and result.pairs:
                values[name].append(result.recall)
            elif name == "ASD" and result.pairs:
                values[name].append(result.asd)
            elif name.startswith("Stability"):
                values[name].append(result.stability)

    n_obj = np.array([s.num_objects for s in rooms])
    print(f"# bench_metrics  {time.strftime('%Y-%m-%d')}  {platform.processor() or platform.machine()}  "
          f"rooms={len(rooms)}  objects/room mean {n_obj.mean():.1f} (min {n_obj.min()}, max {n_obj.max()})  "
          f"perturb={args.perturb} m  source: {source}")
    print("| metric | mean s/room | median s/room | max s/room | first room s | mean value |")
    print("|---|---|---|---|---|---|")
    for name, ts in times.items():
        ts = np.array(ts)
        value = f"{np.nanmean(values[name]):.3f}" if values.get(name) else ""
        print(f"| {name} | {ts.mean():.3f} | {np.median(ts):.3f} | {ts.max():.3f} | {ts[0]:.3f} | {value} |")
    per_room = sum(np.mean(times[n]) for n in metrics if not n.startswith("FID"))
    print(f"| **all but FID** | {per_room:.3f} | | | | 100 rooms: {100 * per_room:.0f} s "
          f"(1 process{', mean x 100' if len(rooms) != 100 else ''}) |")


if __name__ == "__main__":
    main()
