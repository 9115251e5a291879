"""spread-evaluate cost: seconds per room for each metric, the total for N rooms without FID, and the
speed-up from 1 to 2 Ray workers, all in one run. Prints one table.

    python benchmarks/bench_evaluate.py --dataset DIR [--rooms 100] [--substeps 4 1] [--out /tmp/bench_evaluate]

Rooms: the first ``--rooms`` scene files of ``DIR/test`` (a dataset folder from ``spread-generate``; it is
also the reference and the asset library). Each configuration is a complete :func:`run_evaluation`
(``resume=false``, FID off, no renders, no logger) on a private local Ray cluster, timed wall-clock from
the call to ``metrics.json`` — Ray start, worker imports and cold caches included. Per-metric seconds are
the workers' own timings (``per_scene.jsonl`` ``seconds``) of the 1-worker run, where nothing competes.
``--substeps`` lists the Stability protocol's internal steps per 1/60 s protocol step to compare
(4 = the protocol's 1/240 s; the first value is the one timed with 1 and 2 workers).
FID is timed as the protocol render alone (clean-fid's weights are not on this machine).
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def evaluate(scenes: Path, dataset: Path, out: Path, workers: int, substeps: int) -> tuple[float, dict, list]:
    """(wall seconds, metrics, records) of one evaluation with ``workers`` Ray workers."""
    from spread.evaluation import EvalProtocol, EvaluationConfig, FIDConfig, run_evaluation
    from spread.runtime import RaySettings

    cfg = EvaluationConfig(scenes=str(scenes), reference=str(dataset), out_dir=str(out), resume=False, renders=0,
                           progress=False, chunk_size=2, protocol=EvalProtocol(stability_substeps=substeps),
                           fid=FIDConfig(enabled=False), ray=RaySettings(num_cpus=workers))
    t0 = time.perf_counter()
    result = run_evaluation(cfg)
    return time.perf_counter() - t0, result.metrics, result.records


def render_seconds(files: list[Path], dataset: Path) -> float:
    """Mean seconds of the FID protocol render per room (warm: after one untimed render)."""
    from spread.assets import AssetLibrary
    from spread.metrics import fid_render
    from spread.scene import read_scene

    library = AssetLibrary.load(dataset / "assets")
    scenes = [read_scene(f, assets=library) for f in files]
    fid_render(scenes[0], library)
    t0 = time.perf_counter()
    for s in scenes:
        fid_render(s, library)
    return (time.perf_counter() - t0) / len(scenes)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--dataset", type=Path, required=True, help="dataset folder (assets/ + test/)")
    ap.add_argument("--rooms", type=int, default=100)
    ap.add_argument("--substeps", type=int, nargs="+", default=[4, 1])
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "bench_evaluate")
    args = ap.parse_args()
    os.environ.setdefault("WANDB_MODE", "disabled")

    from spread.scene import list_scene_files

    shutil.rmtree(args.out, ignore_errors=True)
    scenes = args.out / "scenes"
    scenes.mkdir(parents=True)
    files = list_scene_files(args.dataset / "test")[:args.rooms]
    for f in files:
        shutil.copy(f, scenes / f.name)
    n = len(files)

    main_substeps = args.substeps[0]
    t1, m1, records = evaluate(scenes, args.dataset, args.out / "w1", 1, main_substeps)
    t2, m2, _ = evaluate(scenes, args.dataset, args.out / "w2", 2, main_substeps)
    others = {s: evaluate(scenes, args.dataset, args.out / f"w2_sub{s}", 2, s) for s in args.substeps[1:]}

    good = [r for r in records if not r.get("error")]
    objects = np.array([r["num_objects"] for r in good])
    per_metric = {k: np.array([r["seconds"][k] for r in good]) for k in ("read", "col_mesh", "grecall", "asd",
                                                                         "stability")}
    print(f"# bench_evaluate  {time.strftime('%Y-%m-%d')}  {platform.machine()} {os.cpu_count()} CPUs  "
          f"load {os.getloadavg()[0]:.1f}  rooms={n} objects/room mean {objects.mean():.1f} "
          f"(min {objects.min()}, max {objects.max()})  dataset {args.dataset}")
    print("| quantity | value |")
    print("|---|---|")
    for k, v in per_metric.items():
        label = "Stability (%d runs x %d steps, %d substeps)" % (m1["protocol"]["stability_runs"],
                                                                  m1["protocol"]["stability_steps"], main_substeps) \
            if k == "stability" else {"read": "read + validate", "col_mesh": "Col_mesh", "grecall": "GRecall",
                                      "asd": "ASD"}[k]
        print(f"| {label}, s/room (1 worker, mean / median / max) | {v.mean():.3f} / {np.median(v):.3f} / "
              f"{v.max():.3f} |")
    print(f"| FID protocol render only, s/room | {render_seconds(files[:20], args.dataset):.3f} |")
    print(f"| sum of metrics but FID, s/room | {sum(v.mean() for v in per_metric.values()):.3f} |")
    print(f"| total {n} rooms without FID, 1 worker (s, wall) | {t1:.1f} |")
    print(f"| total {n} rooms without FID, 2 workers (s, wall) | {t2:.1f} |")
    print(f"| speed-up 1 -> 2 workers | {t1 / t2:.2f}x |")
    for s, (t, m, _) in others.items():
        print(f"| total {n} rooms, 2 workers, Stability with {s} substep(s) (s, wall) | {t:.1f} |")
    for label, m in [(f"{main_substeps} substeps", m2)] + [(f"{s} substep(s)", o[1]) for s, o in others.items()]:
        print(f"| values with {label}: Col_mesh / GRecall / ASD mm / Stability / still | "
              f"{m['col_mesh']:.4f} / {m['grecall']:.4f} / {1000 * m['asd']:.3f} / {m['stability']:.4f} / "
              f"{m['still_fraction']:.4f} |")


if __name__ == "__main__":
    main()
