"""Where a checkpoint's ASD and Col_mesh come from: per supporter category, how far the supported objects are from
what holds them, and which kinds of object pairs collide (issue 33).

    python benchmarks/support_pairs.py CKPT --test DIR [--graphs 16] [--graph-scale 2] [--guided]
           [--guidance guidance.collision=1.5e-2 guidance.gravity=4.0e-3 ...]

Samples the first ``--graphs`` test graphs of ``--test`` once with DDIM-50 (graph ``i`` draws x_T from seed ``i``,
as ``learning_curve.py eval`` at its default seed), optionally refines them (``--guided``: ``guidance=refine`` plus
``--guidance`` overrides), and prints one table: per supporter category (the ten with the largest summed |distance|)
its support pairs, mean |ASD| and mean signed distance (mm; + floating or beside, − sunk: the metric's
min signed distance, :mod:`spread.metrics.support_distance`) and the share of pairs more than 5 cm off; then
the colliding pairs (depth > 1 cm, :mod:`spread.metrics.collision`) by kind: a support pair of the graph, a pair
whose boxes overlap in the test room itself (a chair under a table), or any other pair. One table per mode: the
test rooms, unguided, guided. The guidance is the one ``learning_curve.py eval`` refines with (``guidance=refine``,
the run's own overrides, then ``--guidance``); the sampling loop is that script's too.
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

FAR = 0.05  # metres: a support pair "off" by more than this


def room_boxes(scene, library) -> list[tuple[np.ndarray, np.ndarray]]:
    """World AABBs (lo, hi) of a scene's objects from their asset points, metres."""
    from spread.metrics.geometry import asset_geometry, to_world

    out = []
    for k in range(scene.num_objects):
        g = asset_geometry(library, str(scene.asset_id[k]))
        w = to_world(g.points, scene.rotation[k].astype(float), scene.translation[k].astype(float))
        out.append((w.min(0), w.max(0)))
    return out


def tally(scenes_and_sources, library) -> tuple[dict, dict, float, float]:
    """(per supporter category: signed distances, colliding pairs by kind, Col_mesh, ASD m)."""
    from spread.metrics import scene_collisions, scene_support_distance

    signed, kinds = defaultdict(list), {"support": 0, "room-overlap": 0, "other": 0}
    colliding = objects = 0
    distances = []
    for scene, source in scenes_and_sources:
        c = scene_collisions(scene, library)
        colliding, objects = colliding + c.num_colliding, objects + scene.num_objects
        supports = {tuple(sorted(map(int, p))) for p in source.support_pairs()}
        boxes = None
        for p in c.pairs:
            if p.depth <= c.threshold:
                continue
            a, b = sorted((p.i, p.j))
            if (a, b) in supports:
                kinds["support"] += 1
                continue
            boxes = boxes or room_boxes(source, library)
            lo, hi = np.maximum(boxes[a][0], boxes[b][0]), np.minimum(boxes[a][1], boxes[b][1])
            kinds["room-overlap" if (hi - lo).min() > 0 else "other"] += 1
        for q in scene_support_distance(scene, library).pairs:
            signed[str(scene.category[q.supporter])].append(q.min_signed_distance)
            distances.append(abs(q.min_signed_distance))
    return signed, kinds, colliding / max(objects, 1), float(np.mean(distances)) if distances else float("nan")


def table(mode: str, signed: dict, kinds: dict, col: float, asd: float) -> str:
    rows = sorted(signed.items(), key=lambda kv: -np.sum(np.abs(kv[1])))[:10]
    lines = [f"{mode}: Col_mesh {col:.3f}, ASD {1000 * asd:.1f} mm; colliding pairs: "
             + ", ".join(f"{k} {v}" for k, v in kinds.items()),
             "| supporter | pairs | mean abs (mm) | mean signed (mm) | share > 5 cm |", "|---|---:|---:|---:|---:|"]
    for name, values in rows:
        v = np.asarray(values)
        lines.append(f"| {name} | {len(v)} | {1000 * np.abs(v).mean():.1f} | {1000 * v.mean():+.1f} | "
                     f"{np.mean(np.abs(v) > FAR):.2f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("ckpt")
    p.add_argument("--test", required=True, help="dataset whose test split holds the graphs")
    p.add_argument("--graphs", type=int, default=16)
    p.add_argument("--graph-scale", type=float, default=2.0)
    p.add_argument("--guided", action="store_true", help="also refine the samples (guidance=refine)")
    p.add_argument("--guidance", nargs="*", default=[], help="guidance overrides (guidance.gravity=4e-3)")
    args = p.parse_args(argv)

    import torch

    from learning_curve import run_guidance, sample_graphs
    from spread.sampling.run import DataSplit, SamplingConfig
    from spread.sampling.worker import load_pipeline

    torch.set_num_threads(1)
    # the guidance learning_curve.py eval refines with: guidance=refine, the run's own overrides, then --guidance
    guidance = run_guidance(Path(args.ckpt).parent.parent, args.guidance)[0] if args.guided else None
    pipeline = load_pipeline(SamplingConfig(ckpt=args.ckpt, data=DataSplit(args.test, "test"), out_dir=args.test,
                                            sampler="ddim-50", device="cpu", guidance=guidance,
                                            graph_scale=args.graph_scale))
    data = pipeline.dataset
    n = min(args.graphs, len(data))
    states = defaultdict(list)
    for start in range(0, n, 16):
        idx = list(range(start, min(n, start + 16)))
        sources = [data.read(i) for i in idx]
        scenes, _ = sample_graphs(pipeline, sources, [torch.Generator().manual_seed(i) for i in idx], guided=args.guided)
        for mode, sampled in scenes.items():
            states[mode] += list(zip(sampled, sources))
    print(table("test rooms", *tally([(s, s) for _, s in states["unguided"]], data.library)))
    for mode, pairs in states.items():
        print()
        print(table(mode, *tally(pairs, data.library)))


if __name__ == "__main__":
    main()
