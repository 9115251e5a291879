"""The fixed run behind ``test_registry_regression.py``: per-scene values and ``metrics.json`` numbers of a small
generated dataset's jittered test scenes, and the states of a few guidance steps, as the code computes them.

``python tests/regression.py record`` writes ``tests/data/regression.json`` (done once, before the registries
of issue 22 reshaped evaluation and guidance); the test computes the same run and compares every number.
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np

FIXTURE = Path(__file__).parent / "data" / "regression.json"
#: per_scene.jsonl keys compared (numbers of each scene) and metrics.json keys (numbers of the set).
SCENE_KEYS = ("num_objects", "col_mesh", "grecall", "asd", "stability", "still_fraction",
              "displacement_ok_fraction", "rotation_ok_fraction", "state")
SET_KEYS = ("col_mesh", "grecall", "asd", "stability", "still_fraction", "displacement_ok_fraction",
            "rotation_ok_fraction", "n_scenes", "n_evaluated", "n_failed", "n_objects", "n_colliding_objects",
            "n_support_pairs", "n_graph_pairs", "col_mesh_lo", "col_mesh_hi", "grecall_lo", "grecall_hi", "asd_lo",
            "asd_hi", "stability_lo", "stability_hi", "still_fraction_lo", "still_fraction_hi")


def jittered_scenes(data: Path, out: Path, sigma: float = 0.08, seed: int = 3) -> Path:
    """The test split's scenes with every translation moved by N(0, sigma) metres (seeded), into ``out``."""
    from spread.scene import list_scene_files, read_scene, write_scene

    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    for path in list_scene_files(data / "test"):
        scene = read_scene(path)
        moved = scene.translation + rng.normal(0.0, sigma, scene.translation.shape).astype(np.float32)
        moved[:, 1] = np.maximum(moved[:, 1], scene.translation[:, 1] - 0.02)
        write_scene(scene.with_poses(moved, scene.rotation), out / path.name)
    return out


def evaluation(root: Path) -> dict:
    """Evaluate the jittered scenes of a fresh ``make_dataset`` under ``root``; per-scene and set numbers."""
    sys.path.insert(0, str(Path(__file__).parent))
    from helpers import compose, make_dataset

    from spread.cli.evaluate import main

    data = make_dataset(root, rooms=20, seed=11, max_objects=10)
    scenes = jittered_scenes(data, root / "scenes")
    out = root / "eval"
    main(compose("evaluate", *[f"scenes={scenes}", f"reference={data}", f"out_dir={out}", "logger=none",
                              "progress=false", "renders=0", "fid.enabled=false", "protocol.stability_runs=2",
                              "ray.num_cpus=1", "chunk_size=8"]))
    metrics = json.loads((out / "metrics.json").read_text())
    per_scene = {}
    for line in (out / "per_scene.jsonl").read_text().splitlines():
        record = json.loads(line)
        per_scene[record["scene_id"]] = {k: record.get(k) for k in SCENE_KEYS}
    return {"per_scene": per_scene, "metrics": {k: metrics.get(k) for k in SET_KEYS},
            "per_room_type": metrics.get("per_room_type")}


def guidance_states(root: Path) -> dict:
    """States after 4 ``refine`` iterations (ε̂ = 0) of two box scenes: one interpenetrating, one floating."""
    import torch

    from spread.assets.assemble import box_asset, library_from_specs
    from spread.data import matrix_to_rot6d
    from spread.guidance import SceneGuidance

    lib = library_from_specs(root / "glib", [box_asset("table", (1.0, 0.75, 0.7)), box_asset("cup", (0.08, 0.1, 0.08)),
                                             box_asset("crate", (0.4, 0.3, 0.4))])
    bounds = torch.tensor([-3.0, 0.0, -3.0, 3.0, 2.5, 3.0])
    t = torch.tensor([[[0.0, 0.375, 0.0], [0.1, 0.8, 0.05], [0.3, 0.2, 0.2]],
                      [[0.5, 0.40, 0.0], [0.5, 0.9, 0.0], [0.0, 0.0, 0.0]]], dtype=torch.float64)
    lo, hi = bounds[:3].double(), bounds[3:].double()
    R = torch.eye(3, dtype=torch.float64).expand(2, 3, 3, 3)
    x = torch.cat([2 * (t - lo) / (hi - lo) - 1, matrix_to_rot6d(R)], -1)
    mask = torch.tensor([[True, True, True], [True, True, False]])
    phys = torch.zeros(2, 3, 3, dtype=torch.long)
    phys[0, 0, 1] = 1
    phys[1, 0, 1] = 1
    g = SceneGuidance({"mode": "refine", "iterations": 4, "collision": 0.02, "gravity": 0.01, "relation": 0.01,
                       "gravity_from": 0.25}, lib, [["table", "cup", "crate"], ["table", "cup"]], phys, mask, bounds)
    out = g.refine(x, lambda x, t: torch.zeros_like(x))
    return {"states": out.tolist()}


def compute(root: Path) -> dict:
    return {"evaluation": evaluation(root / "e"), "guidance": guidance_states(root / "g")}


if __name__ == "__main__" and sys.argv[1:] == ["record"]:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        FIXTURE.parent.mkdir(exist_ok=True)
        FIXTURE.write_text(json.dumps(compute(Path(tmp)), indent=1, sort_keys=True) + "\n")
    print(f"wrote {FIXTURE}")
