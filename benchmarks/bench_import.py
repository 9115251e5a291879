"""Import throughput and metric cost per scene on real-style meshes against the same rooms' procedural meshes.

    python benchmarks/bench_import.py [--rooms 16] [--processes 2] [--work DIR] [--categories ...]

1. Generates ``--rooms`` procedural rooms (spread-generate, ``--categories`` × 2 variants).
2. Writes them in the SPREAD release layout the way public assets ship: every asset a **multi-body** glb
   (one node per convex part, not unioned), its file origin at the bottom centre (not the bbox centre);
   every second asset **open** (the parts' faces that touch the floor removed, as game assets cull them).
3. Imports that folder with ``spread-import`` (default decomposition, CoACD) and once more with
   ``decomposition=hull`` into another folder: assets/s and rooms/s.
4. Evaluates every room with both libraries (Col_mesh, ASD, GRecall, Stability with the protocol's 10
   runs; no FID): seconds per scene and the metric values (same poses, same shapes: they should agree).

Prints one table.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

CATEGORIES = ["dining_table", "chair", "sofa", "bookcase", "nightstand", "bed", "mug", "bowl", "book", "plate",
              "vase", "lamp"]


def write_release(dataset: Path, src: Path) -> int:
    """The dataset's rooms (all splits) and assets in the release layout; returns the number of rooms."""
    import trimesh

    from spread.assets import AssetLibrary
    from spread.scene import PHYSICAL_SUPPORT, read_scene

    lib = AssetLibrary.load(dataset / "assets")
    (src / "meshes").mkdir(parents=True, exist_ok=True)
    used: set[str] = set()
    tags = {"train": [], "val": []}
    for split in ("train", "val", "test"):
        for path in sorted((dataset / split).glob("*.npz")):
            scene = read_scene(path, assets=lib)
            used.update(scene.asset_id.tolist())
            n1 = scene.num_objects + 1
            T = np.zeros((n1, 3))
            R = np.tile(np.eye(3), (n1, 1, 1))
            T[1:], R[1:] = scene.translation, scene.rotation
            centre = np.zeros((n1, 3))
            centre[1:, 1] = [lib[a].extents[1] / 2 for a in scene.asset_id]  # origin at the bottom centre
            regions = np.full((n1, n1), 0, np.int64)
            regions[1:, 1:] = scene.spatial
            np.fill_diagonal(regions, 6)
            rel = [[i + 1, 1, j + 1] for i, j in np.argwhere(scene.physical == PHYSICAL_SUPPORT)]
            tag = f"ProcTHOR-{split}-{path.stem}|room"
            (src / tag).mkdir()
            np.savez(src / tag / "boxes.npz", T_bbox=T, R_bbox=R, bbox_center=centre,
                     obj_names=np.array(["root"] + scene.asset_id.tolist()), regions_bbox=regions,
                     relations=np.array(rel, np.int64).reshape(-1, 3))
            tags["val" if split == "test" else "train"].append(tag)
    (src / "train_test_split.json").write_text(json.dumps(tags))
    for k, aid in enumerate(sorted(used)):
        parts = lib.convex_parts(aid)
        bottom = lib[aid].extents[1] / 2
        scene = trimesh.Scene()
        for p, part in enumerate(parts):
            mesh = trimesh.Trimesh(part.vertices, part.faces, process=False)
            if k % 2 == 1:  # open: cull the faces lying on the floor plane
                on_floor = np.all(np.isclose(mesh.triangles[:, :, 1], -bottom, atol=1e-6), axis=1)
                if 0 < on_floor.sum() < len(mesh.faces):
                    mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[~on_floor], process=False)
            scene.add_geometry(mesh.apply_translation([0.0, bottom, 0.0]), node_name=f"part{p}")
        (src / "meshes" / f"{aid}_unpacked.glb").write_bytes(scene.export(file_type="glb"))
    return sum(len(v) for v in tags.values())


def evaluate(folder: Path) -> dict:
    from spread.evaluation import EvalProtocol
    from spread.evaluation.work import evaluate_scene, worker_library

    protocol = EvalProtocol()
    library = worker_library(str(folder / "assets"))
    records = [evaluate_scene(p, library, protocol) for s in ("train", "val", "test")
               for p in sorted((folder / s).glob("*.npz"))]
    good = [r for r in records if not r.get("error")]
    seconds = {m: float(np.median([r["seconds"][m] for r in good])) for m in ("col_mesh", "asd", "stability")}
    from spread.evaluation.aggregate import summary_values

    values = summary_values(records, protocol)
    return {"seconds": seconds, "values": values, "failed": len(records) - len(good)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rooms", type=int, default=16)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--categories", nargs="+", default=CATEGORIES)
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one)")
    args = parser.parse_args()

    from spread.importers.run import ImportConfig, import_dataset
    from spread.procgen.dataset import DatasetConfig, generate_dataset
    from spread.procgen.room_types import RoomConfig

    with tempfile.TemporaryDirectory() as tmp:
        work = args.work or Path(tmp)
        data = work / "procedural"
        if not (data / "manifest.json").exists():
            generate_dataset(data, DatasetConfig(rooms=args.rooms, processes=args.processes, renders=0,
                                                 asset_categories=list(args.categories), asset_variants=2,
                                                 room=RoomConfig(max_objects=12)), progress=False)
        src = work / "release"
        if not src.exists():
            write_release(data, src)
        runs = {}
        for name, method in (("imported (coacd)", "coacd"), ("imported (hull)", "hull")):
            out = work / f"out_{method}"
            t0 = time.perf_counter()
            manifest = import_dataset(ImportConfig("spread_release", str(src), str(out), processes=args.processes,
                                                   progress=False, renders=0, decomposition=method))
            runs[name] = {"manifest": manifest, "wall": time.perf_counter() - t0, "folder": out}
        evals = {"procedural": evaluate(data)}
        for name in runs:
            evals[name] = evaluate(runs[name]["folder"])

    print("\n| quantity | procedural | imported (coacd) | imported (hull) |")
    print("|---|---:|---:|---:|")
    m = {k: v["manifest"] for k, v in runs.items()}
    print(f"| rooms / assets | {sum(m['imported (coacd)']['counts'].values())} / {m['imported (coacd)']['assets']} | "
          f"{sum(m['imported (coacd)']['counts'].values())} / {m['imported (coacd)']['assets']} | "
          f"{sum(m['imported (hull)']['counts'].values())} / {m['imported (hull)']['assets']} |")
    print(f"| open meshes | 0 | {m['imported (coacd)']['meshes']['open']} | {m['imported (hull)']['meshes']['open']} |")
    for key, label in (("assets_per_second", "import: assets/s"), ("rooms_per_second", "import: rooms/s")):
        print(f"| {label} | – | {m['imported (coacd)']['this_run'][key]} | {m['imported (hull)']['this_run'][key]} |")
    print(f"| import: wall s | – | {runs['imported (coacd)']['wall']:.0f} | {runs['imported (hull)']['wall']:.0f} |")
    h = m["imported (coacd)"]["decomposition"]["hausdorff_m"]
    print(f"| decomposition Hausdorff median / max (mm) | exact parts | {1000 * h['median']:.1f} / {1000 * h['max']:.1f} | "
          f"{1000 * m['imported (hull)']['decomposition']['hausdorff_m']['median']:.1f} / "
          f"{1000 * m['imported (hull)']['decomposition']['hausdorff_m']['max']:.1f} |")
    for metric in ("col_mesh", "asd", "stability"):
        print(f"| s per scene: {metric} (median) | " + " | ".join(f"{evals[k]['seconds'][metric]:.3f}" for k in evals) + " |")
    for metric in ("col_mesh", "grecall", "asd", "stability", "still_fraction"):
        print(f"| {metric} | " + " | ".join("null" if evals[k]["values"][metric] is None else
                                           f"{evals[k]['values'][metric]:.4f}" for k in evals) + " |")
    print(f"| failed scenes | " + " | ".join(str(evals[k]["failed"]) for k in evals) + " |")


if __name__ == "__main__":
    main()
