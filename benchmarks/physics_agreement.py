"""Stability with pybullet and with MuJoCo on the same rooms: per-room agreement, set ordering, cost, pictures.

    python benchmarks/physics_agreement.py --assets DATA/assets --set gt=DATA/test --set jit05=J5 \
        --set jit15=J15 --out /tmp/agree [--rooms 100] [--processes 2] [--noise-floor] [--pictures 4]

Each (engine, set, room) is one :func:`spread.metrics.scene_stability` with the protocol's constants
(10 runs × 100 steps of 1/60 s of ``--pybullet-substeps`` / ``--substeps`` (MuJoCo) internal steps each
(4: the protocol's 1/240 s), jitter 0.5 mm, seeds from the scene
ids as ``spread-evaluate`` draws them). Engines: ``pybullet`` (the reference), ``mujoco``
(:class:`spread.physics.MujocoParams` defaults, ``--mujoco key=value`` to override) and, with
``--noise-floor``, ``pybullet@seed1``: pybullet again with another evaluation seed (other sub-millimetre
jitters), i.e. how much a room's Stability moves when nothing but the jitter changes — the floor under
which no engine can agree per room. Results go to ``OUT/<engine>/<set>.jsonl`` (a rerun skips rooms
already there). The table: per set, the mean Stability of each engine, per-room |difference|
(mean / max / rooms over 0.05), the rank correlation of rooms, still-object shares and CPU seconds per
room (process time, so other jobs on the machine inflate it less than wall time). ``--pictures N`` writes
``OUT/pictures/<set>_<room>.png`` for the N rooms that differ most: rows = top view and front view,
columns = the scene, its pybullet run, its MuJoCo run (the run where the engines differ most; same jitter).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

ENGINES = ("pybullet", "mujoco", "pybullet@seed1")
_STATE: dict = {}


def _world(engine: str, substeps: int, mujoco_overrides: dict):
    from spread.metrics import STABILITY_DT

    key = (engine.split("@")[0], substeps, tuple(sorted(mujoco_overrides.items())))
    if key not in _STATE:
        step = STABILITY_DT / substeps
        if key[0] == "pybullet":
            from spread.physics import PhysicsParams, PhysicsWorld

            _STATE[key] = PhysicsWorld(PhysicsParams(time_step=step))
        else:
            from spread.physics import MujocoParams, MujocoWorld

            _STATE[key] = MujocoWorld(MujocoParams(**{"time_step": step, **mujoco_overrides}))
    return _STATE[key]


def _library(assets: str):
    if assets not in _STATE:
        from spread.assets import AssetLibrary

        _STATE[assets] = AssetLibrary.load(assets)
    return _STATE[assets]


def measure(task: tuple) -> tuple:
    """One (engine, set, file): the room's Stability record."""
    engine, label, path, assets, substeps, overrides = task
    from spread.metrics import scene_seed, scene_stability
    from spread.scene import read_scene

    library = _library(assets)
    scene = read_scene(path, assets=library)
    base_seed = 1 if engine.endswith("@seed1") else 0
    world = _world(engine, substeps, overrides)
    t0, c0, s0 = time.perf_counter(), time.process_time(), getattr(world, "steps_simulated", None)
    r = scene_stability(scene, library, seed=scene_seed(scene.scene_id, base_seed), world=world)
    record = {"scene_id": scene.scene_id, "num_objects": scene.num_objects, "stability": r.stability,
              "still_fraction": r.still_fraction, "unchanged": r.unchanged, "pairs": r.pairs,
              "cpu_s": time.process_time() - c0, "wall_s": time.perf_counter() - t0}
    if s0 is not None:  # MuJoCo: internal steps taken (fewer than runs × steps × substeps when every body sleeps)
        record["internal_steps"] = world.steps_simulated - s0
    return engine, label, record


def _read(path: Path) -> dict:
    out = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                continue
            out[rec["scene_id"]] = rec
    return out


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    from scipy.stats import spearmanr

    if len(a) < 3 or np.ptp(a) == 0 or np.ptp(b) == 0:
        return float("nan")
    return float(spearmanr(a, b).statistic)


def side_view(scene):
    """The scene turned −90° about x (room dropped): a top-down render of it is a front view, looking along
    −z with +y up the image (rows grow with the new +z = old −y)."""
    from spread.scene import Scene

    Rx = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # old y → new −z, old z → new y
    t = np.asarray(scene.translation, np.float64) @ Rx.T
    R = np.einsum("ij,njk->nik", Rx, np.asarray(scene.rotation, np.float64))
    return Scene(scene.scene_id, scene.asset_id, scene.category, t.astype(np.float32), R.astype(np.float32),
                 scene.spatial, scene.physical, room=None)


def pictures(rows: list, sets: dict, assets: str, substeps: dict, overrides: dict, out: Path) -> list[Path]:
    """Render the rooms of ``rows`` ((label, scene_id, run) each); returns the written files."""
    from dataclasses import replace

    from spread.metrics import STABILITY_RUNS, scene_seed
    from spread.physics import simulate_runs
    from spread.render import TopDownRenderSettings, render_grid, render_topdown, save_png
    from spread.scene import read_scene

    library = _library(assets)
    written = []
    for label, scene_id, run in rows:
        scene = read_scene(Path(sets[label]) / f"{scene_id}.npz", assets=library)
        finals = []
        for engine in ("pybullet", "mujoco"):
            runs = simulate_runs(scene, library, runs=STABILITY_RUNS, seed=scene_seed(scene.scene_id, 0),
                                 world=_world(engine, substeps[engine], overrides))
            finals.append(scene.with_poses(runs.translation[run].astype(np.float32),
                                           runs.rotation[run].astype(np.float32)))
        views = [scene, *finals]
        top = TopDownRenderSettings(image_size=320, floor=(235, 235, 235))
        bounds = _bounds([v for v in views], library)
        top = replace(top, bounds=(bounds[0], bounds[2], bounds[1], bounds[3]))
        side = [side_view(v) for v in views]
        sb = _bounds(side, library)
        front = TopDownRenderSettings(image_size=320, bounds=(sb[0], sb[2], sb[1], sb[3]))
        images = [render_topdown(v, library, top) for v in views] + [render_topdown(v, library, front) for v in side]
        path = out / f"{label}_{scene_id}.png"
        save_png(render_grid(images, ncols=3), path)
        written.append(path)
    return written


def _bounds(scenes, library) -> tuple[float, float, float, float]:
    """(x_min, x_max, z_min, z_max) over the posed objects of ``scenes``, clipped to ±4 m of the first
    scene's objects (a body flung far away must not shrink the picture)."""
    from spread.render.topdown import posed_meshes

    v0 = np.concatenate([p.vertices for p in posed_meshes(scenes[0], library)])
    lo0, hi0 = v0.min(0) - 4.0, v0.max(0) + 4.0
    v = np.concatenate([np.clip(p.vertices, lo0, hi0) for s in scenes for p in posed_meshes(s, library)])
    return float(v[:, 0].min()), float(v[:, 0].max()), float(v[:, 2].min()), float(v[:, 2].max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--assets", required=True)
    ap.add_argument("--set", action="append", required=True, metavar="LABEL=DIR", help="a folder of scene files")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--rooms", type=int, default=100, help="first N scene files of each set")
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--substeps", type=int, default=4, help="MuJoCo's internal steps per protocol step of 1/60 s")
    ap.add_argument("--pybullet-substeps", type=int, default=4, help="pybullet's (4: the protocol's reference)")
    ap.add_argument("--engines", nargs="+", default=["pybullet", "mujoco"], choices=ENGINES)
    ap.add_argument("--noise-floor", action="store_true", help="also pybullet with evaluation seed 1")
    ap.add_argument("--mujoco", nargs="*", default=[], metavar="KEY=VALUE", help="MujocoParams overrides")
    ap.add_argument("--pictures", type=int, default=0, help="render the N rooms that differ most")
    ap.add_argument("--report-only", action="store_true", help="measure nothing: tabulate the rooms already done")
    a = ap.parse_args()
    from spread.scene import list_scene_files

    sets = dict(s.split("=", 1) for s in a.set)
    overrides = {k: eval(v, {}) for k, v in (kv.split("=", 1) for kv in a.mujoco)}  # numbers / tuples only
    engines = list(a.engines) + (["pybullet@seed1"] if a.noise_floor and "pybullet@seed1" not in a.engines else [])
    substeps = {e: a.substeps if e == "mujoco" else a.pybullet_substeps for e in engines}
    sub = {e: "" if n == 4 else f"_sub{n}" for e, n in substeps.items()}
    tag = "".join(f"_{k}{v}" for k, v in sorted(overrides.items()))
    files_of = {label: list_scene_files(d)[:a.rooms] for label, d in sets.items()}
    store = {(e, label): a.out / (e.replace("@", "_") + sub[e] + (tag if e == "mujoco" else "")) / f"{label}.jsonl"
             for e in engines for label in sets}
    done = {k: _read(p) for k, p in store.items()}
    tasks = [(e, label, str(f), a.assets, substeps[e], overrides) for e in engines
             for label, files in files_of.items() for f in files if f.stem not in done[(e, label)]]
    if tasks and not a.report_only:
        import multiprocessing

        from tqdm import tqdm

        with multiprocessing.get_context("spawn").Pool(a.processes) as pool:
            for engine, label, record in tqdm(pool.imap_unordered(measure, tasks), total=len(tasks), desc="rooms"):
                path = store[(engine, label)]
                path.parent.mkdir(parents=True, exist_ok=True)
                with open(path, "a") as fh:
                    fh.write(json.dumps(record) + "\n")
                done[(engine, label)][record["scene_id"]] = record

    if not {"pybullet", "mujoco"} <= set(engines):
        print(f"measured: {', '.join(engines)} (the table needs both pybullet and mujoco)")
        return
    print(f"| set | rooms | pybullet | MuJoCo | per-room abs diff mean / median / max | rooms diff > 0.05 | "
          f"rank corr. | pybullet other seed: abs diff mean / max | still pb / mj | CPU s/room pb / mj |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    worst = []
    means = {}
    for label, files in files_of.items():
        ids = [f.stem for f in files if all(f.stem in done[(e, label)] for e in engines)]
        get = lambda e, key: np.array([done[(e, label)][i][key] for i in ids], np.float64)  # noqa: E731
        pb, mj = get("pybullet", "stability"), get("mujoco", "stability")
        diff = mj - pb
        floor = ""
        if "pybullet@seed1" in engines:
            d1 = np.abs(get("pybullet@seed1", "stability") - pb)
            floor = f"{d1.mean():.4f} / {d1.max():.4f}"
        means[label] = (pb.mean(), mj.mean())
        print(f"| {label} | {len(ids)} | {pb.mean():.4f} | {mj.mean():.4f} | {np.abs(diff).mean():.4f} / "
              f"{np.median(np.abs(diff)):.4f} / {np.abs(diff).max():.4f} | {(np.abs(diff) > 0.05).sum()} | "
              f"{spearman(pb, mj):.2f} | {floor} | {get('pybullet', 'still_fraction').mean():.4f} / "
              f"{get('mujoco', 'still_fraction').mean():.4f} | {get('pybullet', 'cpu_s').mean():.2f} / "
              f"{get('mujoco', 'cpu_s').mean():.2f} |")
        for k, i in enumerate(ids):
            u_pb = np.array(done[("pybullet", label)][i]["unchanged"])
            u_mj = np.array(done[("mujoco", label)][i]["unchanged"])
            worst.append((abs(diff[k]), label, i, int(np.argmax(np.abs(u_pb - u_mj)))))
    order_pb = sorted(means, key=lambda s: -means[s][0])
    order_mj = sorted(means, key=lambda s: -means[s][1])
    print(f"\nordering by Stability: pybullet {' > '.join(order_pb)}; MuJoCo {' > '.join(order_mj)}"
          f" ({'same' if order_pb == order_mj else 'DIFFERENT'})")
    if a.pictures:
        worst.sort(reverse=True)
        rows = [(label, i, run) for _, label, i, run in worst[:a.pictures]]
        for (d, label, i, run), path in zip(worst, pictures(rows, sets, a.assets, substeps, overrides,
                                                            a.out / "pictures")):
            print(f"picture: {path} ({label} {i}, |diff| {d:.3f}, run {run})")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
