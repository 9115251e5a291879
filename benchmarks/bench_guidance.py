"""Guidance cost: per step and per scene against object count, and full guided sampling latency.

    python benchmarks/bench_guidance.py --data DATASET [--ckpt TINY.ckpt] [--sizes 10 25 50]
        [--iterations 100] [--batch 8] [--samplers ddim-50 dpmsolver++-20] [--release] [--threads 1]
        [--detect auto host device]

Part 1 (guidance alone, no network). Scenes of N objects are made by laying the dataset's rooms
(test, then val, then train) side by side along x, 0.5 m apart, with their graphs block-diagonal (the
last room cut to fit, lowest objects first, so supporters stay); bounds are the tiled scene's extent
± 1 m. Two states each: the settled ground truth (objects touching their supporters) and the same
jittered by N(0, 5 cm) in x and z, N(0, 1 cm) in y and N(0, 0.1 rad) in yaw (penetrations, floating,
overhangs, like a generated scene). Each row runs the ``refine`` loop with ε̂ = 0 (so only guidance
works) for ``--iterations`` iterations, one scene per batch: per step = total / iterations; per scene
= the total; the split is the guidance's own stats (BVH = broad phase + triangle-pair search, penalty = the three
terms' forward and backward, torch). Each row once per ``--detect`` path (``guidance.detect``: ``host`` = python-fcl
and scipy hulls, ``device`` = spread.guidance.dense on the states' device, here the CPU), with the host reads of one
step at the jittered state (``OperatorCounter``: nonzero, item, ... — the host path's copies of the poses to numpy
are not counted, as on CPU tensors they are no copy).

Part 2 (full sampling). A batch of the first ``--batch`` test scenes, encoded as ``spread-sample``
does, sampled with the tiny geometry model (``--ckpt`` or untrained) with guidance none / paper /
refine for each sampler; per scene = batch wall / batch size. Network time in ``paper`` mode is the
wall time less the guidance's own; in ``refine`` mode the sampler's plus the refinement's network
calls. ``--release`` adds the release's pipeline: DDPM-1000 then 100 refinement iterations. Prints
one markdown table per part.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

GAP = 0.5  # metres between tiled rooms


def tiled_scene(scenes, library, n: int):
    """(asset ids, translation (n, 3), rotation (n, 3, 3), physical (n, n)) of rooms laid along x."""
    from spread.relations import scene_aabbs

    ids, ts, Rs, blocks = [], [], [], []
    x_at = 0.0
    for scene in scenes:
        need = n - len(ids)
        if need <= 0:
            break
        order = np.argsort(scene.translation[:, 1], kind="stable")[:need]  # lowest first: supporters stay
        order.sort()
        lo, hi = scene_aabbs(scene.translation, scene.rotation, scene.asset_id, library)
        shift = np.array([x_at - lo[order, 0].min(), 0.0, 0.0])
        x_at += hi[order, 0].max() - lo[order, 0].min() + GAP
        ids += [str(a) for a in scene.asset_id[order]]
        ts.append(scene.translation[order] + shift)
        Rs.append(scene.rotation[order])
        blocks.append(scene.physical[np.ix_(order, order)])
    if len(ids) < n:
        raise SystemExit(f"bench_guidance: the dataset has only {len(ids)} objects, {n} asked")
    physical = np.zeros((n, n), np.int64)
    k = 0
    for block in blocks:
        physical[k:k + len(block), k:k + len(block)] = block
        k += len(block)
    return ids, np.concatenate(ts), np.concatenate(Rs), physical


def jitter(translation, rotation, seed: int):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    t = translation + rng.normal(0, [0.05, 0.01, 0.05], translation.shape)
    yaw = Rotation.from_rotvec(np.outer(rng.normal(0, 0.1, len(t)), [0, 1, 0])).as_matrix()
    return t, yaw @ rotation


def to_state(translation, rotation, bounds):
    import torch

    from spread.data import matrix_to_rot6d

    t = torch.as_tensor(translation, dtype=torch.float32)
    lo, hi = bounds[:3], bounds[3:]
    R = torch.as_tensor(rotation, dtype=torch.float32)
    return torch.cat([2 * (t - lo) / (hi - lo) - 1, matrix_to_rot6d(R)], -1)


def part_guidance(scenes, library, sizes, iterations: int, detects=("auto",)) -> None:
    import torch

    from spread.guidance import GuidanceConfig, SceneGuidance
    from spread.model.opcount import OperatorCounter

    print(f"\n| N | state | detect | support pairs | tri pairs at start | step at start (ms) | host reads / step "
          f"| tri pairs / step | per step (ms) | BVH (ms) | penalty (ms) | per scene, {iterations} it. (s) | BVH share "
          f"| penalty share |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for n in sizes:
        ids, t, R, physical = tiled_scene(scenes, library, n)
        for label, (tt, RR), detect in [(lab, pose, d) for lab, pose in (("ground truth", (t, R)),
                                                                          ("jittered", jitter(t, R, n)))
                                        for d in detects]:
            lo = np.minimum(tt.min(0), 0) - 1.0
            hi = tt.max(0) + 1.0
            bounds = torch.tensor(np.concatenate([lo, hi]), dtype=torch.float32)
            x = to_state(tt, RR, bounds)[None]
            config = GuidanceConfig("refine", iterations=iterations, detect=detect)
            guidance = SceneGuidance(config, library, [ids], torch.as_tensor(physical)[None],
                                     torch.ones(1, n, dtype=torch.bool), bounds)
            guidance.step(x)  # warm: BVHs and caches
            start_pairs = guidance.stats["last_colliding_pairs"]
            t0 = time.perf_counter()
            for _ in range(10):
                guidance.step(x)
            at_start = (time.perf_counter() - t0) / 10
            with OperatorCounter() as counter:
                guidance.step(x)
            guidance.reset_stats()
            t0 = time.perf_counter()
            guidance.refine(x, lambda x_t, _: torch.zeros_like(x_t))
            wall = time.perf_counter() - t0
            s = guidance.stats
            k = s["steps"]
            print(f"| {n} | {label} | {detect} | {int((physical == 1).sum())} | {start_pairs} | {1000 * at_start:.1f} | "
                  f"{counter.syncs} | {s['colliding_pairs'] / k:.0f} | {1000 * wall / k:.1f} | {1000 * s['bvh_s'] / k:.1f} | "
                  f"{1000 * s['penalty_s'] / k:.1f} | {wall:.2f} | {s['bvh_s'] / wall:.0%} | "
                  f"{s['penalty_s'] / wall:.0%} |", flush=True)


def part_sampling(args, library) -> None:
    import torch

    from spread.data import SceneDataset, collate_scenes, load_stats
    from spread.guidance import GuidanceConfig, SceneGuidance
    from spread.model.diffusion import denoise
    from spread.model.module import SceneDiffusion
    from spread.sampling.pipeline import guidance_callback
    from spread.sampling.worker import checkpoint_data_settings

    if args.ckpt:
        from spread.methods import module_from_checkpoint
        from spread.safe_load import load_checkpoint

        checkpoint = load_checkpoint(args.ckpt)  # weights only: no code runs from the file
        model = module_from_checkpoint(checkpoint, source=str(args.ckpt)).eval()
        data = checkpoint_data_settings(checkpoint, model)
    else:
        bounds = load_stats(os.path.join(args.data, "stats.json"))["bounds_translations"]
        from spread.configs import model_config

        model = SceneDiffusion("geometry", model_config("tiny"), bounds=bounds).eval()
        data = {"num_points": model.config.num_points, "seed": 0}
    dataset = SceneDataset(args.data, "test", library=library, num_points=data["num_points"], seed=data["seed"])
    items = [i % len(dataset) for i in range(args.batch)]
    batch = collate_scenes([dataset[i] for i in items])
    asset_ids = [[str(a) for a in dataset.read(i).asset_id] for i in items]
    B = len(items)
    objects = batch["num_objects"].float()
    print(f"\nFull sampling: batch of {B} test scenes ({objects.mean():.1f} objects mean, {int(objects.max())} max), "
          f"tiny geometry model ({'trained' if args.ckpt else 'untrained'}).\n")
    print("| sampler | guidance | per scene (s) | guidance per scene (s) | BVH | penalty | network + sampler "
          "| guided steps | tri pairs / step |")
    print("|---|---|---|---|---|---|---|---|---|")
    runs = [(s, m) for s in args.samplers for m in ("none", "paper", "refine")]
    if args.release:
        runs.append(("ddpm-1000", "refine"))
    for sampler, mode in runs:
        guidance = None
        if mode != "none":
            config = GuidanceConfig(mode, iterations=args.iterations, detect=args.detect[0])
            guidance = SceneGuidance(config, library, asset_ids, batch["physical"], batch["mask"], model.network.bounds)
        t0 = time.perf_counter()
        callbacks = [guidance_callback(guidance)] if guidance is not None else []
        with torch.no_grad():
            denoise(model.denoising(batch), sampler, torch.Generator().manual_seed(0), callbacks)
        wall = time.perf_counter() - t0
        if guidance is None:
            print(f"| {sampler} | none | {wall / B:.2f} | 0 | 0% | 0% | 100% | 0 | 0 |", flush=True)
            continue
        s = guidance.stats
        own = s["bvh_s"] + s["penalty_s"]
        pairs = s["colliding_pairs"] / max(s["steps"], 1)
        print(f"| {sampler} | {mode} | {wall / B:.2f} | {own / B:.2f} | {s['bvh_s'] / wall:.0%} | "
              f"{s['penalty_s'] / wall:.0%} | {(wall - own) / wall:.0%} | {s['steps']} | {pairs:.0f} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True, help="dataset folder (rooms and its assets/ library)")
    ap.add_argument("--ckpt", default=None, help="tiny geometry checkpoint (default: untrained tiny model)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[10, 25, 50])
    ap.add_argument("--iterations", type=int, default=100)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--samplers", nargs="*", default=["ddim-50", "dpmsolver++-20"])
    ap.add_argument("--release", action="store_true", help="also DDPM-1000 + refine (slow on CPU)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--detect", nargs="+", default=["auto"], choices=["auto", "host", "device"],
                    help="guidance.detect paths to compare in part 1 (part 2 takes the first)")
    args = ap.parse_args()

    import torch

    from spread.assets.library import AssetLibrary
    from spread.scene import read_scene

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    library = AssetLibrary.load(os.path.join(args.data, "assets"))
    files = [os.path.join(args.data, split, f) for split in ("test", "val", "train")
             if os.path.isdir(os.path.join(args.data, split))
             for f in sorted(os.listdir(os.path.join(args.data, split))) if f.endswith(".npz")]
    print(f"# bench_guidance  {time.strftime('%Y-%m-%d')}  {platform.machine()}  {os.cpu_count()} cores, "
          f"torch {torch.__version__}, {args.threads} thread(s), load avg {os.getloadavg()[0]:.1f}; "
          f"dataset {args.data}")
    scenes = [read_scene(f, assets=library) for f in files[:max(args.sizes) // 2 + 8]]
    part_guidance(scenes, library, args.sizes, args.iterations, args.detect)
    if args.samplers or args.release:
        part_sampling(args, library)


if __name__ == "__main__":
    main()
