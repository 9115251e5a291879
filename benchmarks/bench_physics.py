"""Stability engines side by side: seconds per room for pybullet and MuJoCo, 100 rooms with every metric but FID
on the local cores, runs stepped on threads, and where MuJoCo's time goes. Prints one table.

    python benchmarks/bench_physics.py --dataset DIR [--rooms 100] [--workers 2]
        [--configs pybullet:4 mujoco:4 mujoco:4:sleep mujoco:1] [--thread-rooms 10] [--profile-rooms 5]
        [--warp-rooms 3 --warp-device cpu]

Rooms: the first ``--rooms`` scene files of ``DIR/test`` (``DIR`` from ``spread-generate``: also the reference
and the asset library). Each config ``ENGINE:SUBSTEPS`` is one complete :func:`run_evaluation` (``resume``
off, FID off, no renders, no logger, ``--workers`` local Ray workers, chunks of 2; ``:sleep`` adds
``protocol.physics_sleep=true``) timed wall-clock from
the call to ``metrics.json`` (Ray start, imports, cold caches included); per-metric seconds are the
workers' own (``per_scene.jsonl``). ``--thread-rooms``: one process, MuJoCo, the protocol's 10 runs of
each room stepped by 1 thread vs ``mujoco.rollout`` on 2 threads (wall seconds). ``--profile-rooms``:
MuJoCo's own timers over one run of each room (ms per internal step: collision, constraint assembly,
solver), the profile of what is left. ``--warp-rooms``: one process, the protocol's 10 runs of each room as
one batch of MuJoCo Warp worlds on ``--warp-device`` against C MuJoCo on one thread: wall and CPU seconds of
the first room (kernel compile or cache load) and of the rest, and how far the final poses differ.
(``--configs mujoco_warp:4`` runs MuJoCo Warp through the whole evaluation like the other engines.)
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


def evaluate(scenes: Path, dataset: Path, out: Path, workers: int, engine: str, substeps: int, sleep: bool = False):
    from spread.evaluation import EvalProtocol, EvaluationConfig, FIDConfig, run_evaluation
    from spread.runtime import RaySettings

    cfg = EvaluationConfig(scenes=str(scenes), reference=str(dataset), out_dir=str(out), resume=False, renders=0,
                           progress=False, chunk_size=2,
                           protocol=EvalProtocol(stability_substeps=substeps, physics=engine, physics_sleep=sleep),
                           fid=FIDConfig(enabled=False),
                           ray=RaySettings(num_cpus=workers))
    t0 = time.perf_counter()
    result = run_evaluation(cfg)
    return time.perf_counter() - t0, result.metrics, result.records


def thread_timing(files, library, rooms: int) -> tuple[float, float, bool]:
    """(wall s/room with 1 thread, with 2 threads, identical results) for the protocol's runs in MuJoCo."""
    from spread.metrics import scene_stability
    from spread.physics import MujocoParams, MujocoWorld
    from spread.scene import read_scene

    scenes = [read_scene(f, assets=library) for f in files[:rooms]]
    out = {}
    for threads in (1, 2):
        world = MujocoWorld(MujocoParams(threads=threads))
        scene_stability(scenes[0], library, world=world)  # warm: asset geometry, thread pool
        t0 = time.perf_counter()
        out[threads] = [scene_stability(s, library, world=world).unchanged for s in scenes]
        out[f"t{threads}"] = (time.perf_counter() - t0) / len(scenes)
        world.close()
    return out["t1"], out["t2"], out[1] == out[2]


def warp_timing(files, library, rooms: int, device: str) -> dict:
    """MuJoCo Warp (one batch of 10 worlds per room) against C MuJoCo on one thread, one process: wall and CPU
    seconds per room of the first room and of the others, the largest final-position difference and whether
    both engines call the same objects still (moved < 1 cm and turned < 0.1 rad) in every run."""
    from spread.metrics import STABILITY_DT, STABILITY_JITTER, STABILITY_RUNS, STABILITY_STEPS, STILL_ANGLE, \
        STILL_DISTANCE
    from spread.physics import MujocoParams, MujocoWarpParams, MujocoWarpWorld, MujocoWorld, displacement_stats, \
        simulate_runs
    from spread.scene import read_scene

    scenes = [read_scene(f, assets=library) for f in files[:rooms]]
    out = {"warp": [], "c": [], "dmax": [], "same_still": True}
    kw = dict(runs=STABILITY_RUNS, steps=STABILITY_STEPS, dt=STABILITY_DT, jitter=STABILITY_JITTER, seed=0)
    t0, c0 = time.perf_counter(), time.process_time()
    warp = MujocoWarpWorld(MujocoWarpParams(time_step=STABILITY_DT / 4, device=device))
    out["init"] = (time.perf_counter() - t0, time.process_time() - c0)
    c_world = MujocoWorld(MujocoParams(time_step=STABILITY_DT / 4))
    for scene in scenes:
        results = {}
        for name, world in (("warp", warp), ("c", c_world)):
            t0, c0 = time.perf_counter(), time.process_time()
            results[name] = simulate_runs(scene, library, world=world, **kw)
            out[name].append((time.perf_counter() - t0, time.process_time() - c0))
        out["dmax"].append(float(np.abs(results["warp"].translation - results["c"].translation).max()))
        still = [(lambda m: (m.distance < STILL_DISTANCE) & (m.angle < STILL_ANGLE))(
            displacement_stats((scene.translation, scene.rotation), results[k])) for k in ("warp", "c")]
        out["same_still"] &= bool((still[0] == still[1]).all())
    out["device"], out["objects"] = warp.device, float(np.mean([s.num_objects for s in scenes]))
    return out


def mujoco_profile(files, library, rooms: int) -> dict:
    """Mean ms per internal step of MuJoCo's timers, and contacts per step, over one protocol run per room."""
    import mujoco

    from spread.physics import MujocoWorld
    from spread.scene import read_scene

    names = {"step": mujoco.mjtTimer.mjTIMER_STEP, "collision (narrow phase)": mujoco.mjtTimer.mjTIMER_COL_NARROW,
             "collision (broad phase)": mujoco.mjtTimer.mjTIMER_COL_BROAD,
             "constraint assembly": mujoco.mjtTimer.mjTIMER_POS_MAKE, "solver": mujoco.mjtTimer.mjTIMER_CONSTRAINT}
    acc = {k: 0.0 for k in names}
    steps, contacts, objects, geoms = 0, 0, 0, 0
    for f in files[:rooms]:
        scene = read_scene(f, assets=library)
        world = MujocoWorld()
        world.load_scene(scene, library)
        world.set_time_step(world.params.time_step)
        for _ in range(400):
            mujoco.mj_step(world.model, world.data)
            contacts += world.data.ncon
        for k, t in names.items():
            acc[k] += world.data.timer[t].duration
        steps += 400
        objects += scene.num_objects
        geoms += int(world.model.ngeom)
    return {**{k: 1e3 * v / steps for k, v in acc.items()}, "contacts per step": contacts / steps,
            "objects per room": objects / rooms, "geoms per room": geoms / rooms}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--dataset", type=Path, required=True, help="dataset folder (assets/ + test/)")
    ap.add_argument("--rooms", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--configs", nargs="*", default=["pybullet:4", "mujoco:4", "mujoco:1"],
                    help="ENGINE:SUBSTEPS[:sleep], ENGINE one of protocol.physics (pybullet, mujoco, mujoco_warp); "
                         ":sleep adds protocol.physics_sleep=true (mujoco); none: skip")
    ap.add_argument("--thread-rooms", type=int, default=10)
    ap.add_argument("--profile-rooms", type=int, default=5)
    ap.add_argument("--warp-rooms", type=int, default=0, help="rooms for the MuJoCo Warp timing (0: none)")
    ap.add_argument("--warp-device", default="auto", help="MuJoCo Warp device: cpu | cuda | auto")
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "bench_physics")
    args = ap.parse_args()
    os.environ.setdefault("WANDB_MODE", "disabled")

    from spread.assets import AssetLibrary
    from spread.scene import list_scene_files

    shutil.rmtree(args.out, ignore_errors=True)
    scenes = args.out / "scenes"
    scenes.mkdir(parents=True)
    files = list_scene_files(args.dataset / "test")[:args.rooms]
    for f in files:
        shutil.copy(f, scenes / f.name)
    loads = [os.getloadavg()[0]]
    runs = {}
    for config in args.configs:
        engine, substeps, *flags = config.split(":")
        runs[config] = evaluate(scenes, args.dataset, args.out / config.replace(":", "_"), args.workers, engine,
                                int(substeps), sleep="sleep" in flags)
        loads.append(os.getloadavg()[0])
    library = AssetLibrary.load(args.dataset / "assets")
    threads = thread_timing(files, library, args.thread_rooms) if args.thread_rooms else None
    profile = mujoco_profile(files, library, args.profile_rooms) if args.profile_rooms else None
    warp = warp_timing(files, library, args.warp_rooms, args.warp_device) if args.warp_rooms else None
    loads.append(os.getloadavg()[0])

    print(f"# bench_physics  {time.strftime('%Y-%m-%d %H:%M')}  {platform.machine()} {os.cpu_count()} CPUs  "
          f"1-min load before/between/after runs {' / '.join(f'{x:.1f}' for x in loads)}  rooms={len(files)} "
          f"workers={args.workers}  dataset {args.dataset}")
    if runs:
        objects = [r["num_objects"] for r in runs[args.configs[0]][2] if not r.get("error")]
        print(f"objects/room mean {np.mean(objects):.1f}")
        print("| engine:substeps | Stability s/room (worker, mean / median / max) | Col_mesh + ASD s/room | "
              f"{len(files)} rooms, all metrics but FID, {args.workers} workers (s, wall) | Stability | still | failed |")
        print("|---|---|---|---|---|---|---|")
    for config, (wall, metrics, records) in runs.items():
        good = [r for r in records if not r.get("error")]
        st = np.array([r["seconds"]["stability"] for r in good])
        other = np.array([r["seconds"]["col_mesh"] + r["seconds"]["asd"] for r in good])
        print(f"| {config} | {st.mean():.3f} / {np.median(st):.3f} / {st.max():.3f} | {other.mean():.3f} | "
              f"**{wall:.1f}** | {metrics['stability']:.4f} | {metrics['still_fraction']:.4f} | "
              f"{len(records) - len(good)} |")
    if threads:
        print(f"\nMuJoCo runs of a room on threads ({args.thread_rooms} rooms, 1 process): 1 thread "
              f"{threads[0]:.3f} s/room, mujoco.rollout on 2 threads {threads[1]:.3f} s/room "
              f"({threads[0] / threads[1]:.2f}x), identical results: {threads[2]}")
    if profile:
        print(f"\nMuJoCo profile (1 run of {args.profile_rooms} rooms, {profile['objects per room']:.1f} objects, "
              f"{profile['geoms per room']:.0f} geoms, {profile['contacts per step']:.0f} contacts per step), "
              "ms per internal step: " + ", ".join(f"{k} {v:.3f}" for k, v in profile.items()
                                                   if k not in ("contacts per step", "objects per room",
                                                                "geoms per room")))

    if warp:
        print(f"\nMuJoCo Warp on {warp['device']} vs C MuJoCo 1 thread ({args.warp_rooms} rooms, "
              f"{warp['objects']:.1f} objects, 10 runs x 400 internal steps, 1 process): world creation "
              f"{warp['init'][0]:.1f} s wall / {warp['init'][1]:.1f} s CPU")
        print("| engine | first room s (wall / CPU) | other rooms s/room (wall / CPU) |\n|---|---|---|")
        for name, label in (("warp", "MuJoCo Warp, 10 worlds per batch"), ("c", "C MuJoCo, 1 thread")):
            first, rest = warp[name][0], np.array(warp[name][1:]).reshape(-1, 2)
            rest_s = f"{rest[:, 0].mean():.2f} / {rest[:, 1].mean():.2f}" if len(rest) else "-"
            print(f"| {label} | {first[0]:.2f} / {first[1]:.2f} | {rest_s} |")
        print("CPU s per room, MuJoCo Warp / C MuJoCo: " + ", ".join(
            f"{a[1]:.1f} / {b[1]:.2f}" for a, b in zip(warp["warp"], warp["c"])))
        print(f"largest final-position difference per room (m): {' '.join(f'{d:.2g}' for d in warp['dmax'])}; "
              f"same still objects in every run: {warp['same_still']}")


if __name__ == "__main__":
    main()
