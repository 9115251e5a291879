"""The guidance's colliding triangle pairs found three ways on the same poses: python-fcl on the host, the device
path (``spread.guidance.dense``) on CPU tensors and, where CUDA is present, on the GPU — and where they differ.

Why: on the H200 (RESULTS.md, fourth GPU slot) the refine rows of ``bench_gpu.py`` counted 758,024 triangle pairs
with ``guidance.detect=device`` against 277,077 with ``host`` — and 276,872 for the device path on this CPU — for
states that depend on the noise only (an initialised network predicts ε̂ ≡ 0). This script finds which stage differs:
the object pairs (broad phase), the candidate face pairs (triangle boxes), the exact triangle test, or the
``max_contacts`` cap, and prints one differing triangle pair with both devices' verdicts.

    python benchmarks/detect_ab.py --data .gpudata/rooms [--scenes 64] [--json OUT.json]

Poses (``--states``): the rooms' objects at the corners of the bounds at random rotations (``corners``), as the refine
rows saw them (``clipped``: a quarter of the objects flattened by degenerate rotations), or at standard-normal states.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import torch


def inputs(data: Path, scenes: int, seed: int, states: str):
    """The rooms' objects (repeated to ``scenes``) at poses decoded from seeded states: ``noise``, standard normal
    (a sampler's x_T); ``clipped``, their signs — what DDIM's first x̂_0 is for an initialised network (ε̂ = 0, so
    x̂_0 = x_T / √ᾱ_T, clipped to ±1): every object at a corner of the bounds, and a quarter of them flattened (their
    two 6-d rotation vectors parallel: a zero column); ``corners``: at the corners, rotations from the noise."""
    from spread.assets.library import AssetLibrary
    from spread.data.stats import load_stats
    from spread.model.poses import poses_from_state
    from spread.scene import read_scene

    library = AssetLibrary.load(data / "assets")
    files = [f for split in ("test", "val", "train") for f in sorted((data / split).glob("*.npz"))]
    if not files:
        raise SystemExit(f"detect_ab: no rooms (*.npz) under {data}/{{test,val,train}}")
    rooms = [read_scene(files[k % len(files)], assets=library) for k in range(scenes)]
    B, N = len(rooms), max(r.num_objects for r in rooms)
    mask = torch.zeros(B, N, dtype=torch.bool)
    for b, r in enumerate(rooms):
        mask[b, :r.num_objects] = True
    bounds = torch.tensor(load_stats(data / "stats.json")["bounds_translations"], dtype=torch.float64).flatten()
    x = torch.randn(B, N, 9, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    if states == "clipped":
        x = x.sign()
    elif states == "corners":
        x[..., :3] = x[..., :3].sign()
    translation, rotation = poses_from_state(x, bounds)
    return library, [list(r.asset_id) for r in rooms], torch.zeros(B, N, N, dtype=torch.long), mask, \
        translation, rotation, bounds


def pairs(guidance, translation, rotation, device, dtype):
    t, R = translation.to(device, dtype), rotation.to(device, dtype)
    world = guidance.meshes.pose(t, R)
    hull = guidance.meshes.hull_points(world)
    t0 = time.perf_counter()
    p = guidance.detect(t, R, hull, world)
    if device.type == "cuda":
        torch.cuda.synchronize()
    rows = torch.stack([p.b, p.i, p.fi, p.j, p.fj], 1).cpu().numpy()
    return {tuple(r) for r in rows.tolist()}, p.object_pairs, time.perf_counter() - t0, world


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path(".gpudata/rooms"))
    ap.add_argument("--scenes", type=int, default=64)
    ap.add_argument("--states", choices=["corners", "clipped", "noise"], default="corners")
    ap.add_argument("--max-contacts", type=int, default=2048)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    from spread.guidance import SceneGuidance
    from spread.guidance.dense import triangles_intersect

    torch.backends.cuda.matmul.allow_tf32 = False
    library, ids, physical, mask, translation, rotation, bounds = inputs(args.data, args.scenes, 0, args.states)
    out: dict = {"scenes": args.scenes, "objects": int(mask.sum()), "gpu": torch.cuda.get_device_name(0)
                 if torch.cuda.is_available() else None}
    ways = [("host", torch.device("cpu")), ("device", torch.device("cpu"))]
    if torch.cuda.is_available():
        ways.append(("device", torch.device("cuda")))
    found = {}
    for caps in (args.max_contacts, 1 << 30):
        for detect, device in ways:
            g = SceneGuidance({"mode": "refine", "detect": detect, "max_contacts": caps}, library, ids, physical,
                              mask, bounds)
            rows, objects, seconds, world = pairs(g, translation, rotation, device, torch.float32)
            key = f"{detect}@{device.type} cap={'none' if caps > 1e8 else caps}"
            found[key] = (rows, world, g)
            out[key] = {"triangle_pairs": len(rows), "object_pairs": objects, "seconds": round(seconds, 3)}
            print(f"{key:28s} triangle pairs {len(rows):>9,}  object pairs {objects:>6,}  {seconds:.2f} s", flush=True)
    # where the device path and python-fcl differ (uncapped, CPU): objects at one pose (coincident faces)?
    host_rows, device_rows = found["host@cpu cap=none"][0], found["device@cpu cap=none"][0]
    flat = (torch.linalg.det(rotation).abs() < 0.5) & mask  # a degenerate rotation squashes the object's mesh
    out["flattened_objects"] = int(flat.sum())
    for name, rows in (("only_device", device_rows - host_rows), ("only_host", host_rows - device_rows)):
        flattened = sum(bool(flat[b, i] or flat[b, j]) for b, i, _, j, _ in rows)
        out[f"{name}@cpu"] = {"triangle_pairs": len(rows), "with a flattened object": flattened}
        print(f"{name} (CPU, uncapped): {len(rows):,} triangle pairs, {flattened:,} of them with a flattened object "
              f"({int(flat.sum())} of {int(mask.sum())} objects are)", flush=True)
    if torch.cuda.is_available():  # where the GPU's device path and the CPU's differ, uncapped: the exact test?
        cpu_rows, cpu_world, g = found["device@cpu cap=none"]
        gpu_rows, gpu_world, _ = found["device@cuda cap=none"]
        only_gpu, only_cpu = sorted(gpu_rows - cpu_rows), sorted(cpu_rows - gpu_rows)
        out["only_gpu"], out["only_cpu"] = len(only_gpu), len(only_cpu)
        out["world_max_diff_m"] = float((gpu_world.cpu() - cpu_world).abs().max())
        print(f"uncapped: {len(only_gpu):,} pairs only on the GPU, {len(only_cpu):,} only on the CPU; posed vertices "
              f"differ by up to {out['world_max_diff_m']:.2e} m", flush=True)
        for name, sample in (("only_gpu", only_gpu[:2000]), ("only_cpu", only_cpu[:2000])):
            if not sample:
                continue
            idx = torch.tensor(sample)
            b, i, fi, j, fj = idx.unbind(1)
            tri = {dev: (g.meshes.triangles(w.to(dev), b.to(dev), i.to(dev), fi.to(dev)),
                         g.meshes.triangles(w.to(dev), b.to(dev), j.to(dev), fj.to(dev)))
                   for dev, w in (("cpu", cpu_world), ("cuda", cpu_world))}  # the same (CPU) vertices on both
            verdict = {dev: triangles_intersect(*tri[dev]).cpu() for dev in tri}
            agree = int((verdict["cpu"] == verdict["cuda"]).sum())
            out[f"{name}_exact_test_agrees"] = f"{agree}/{len(sample)}"
            print(f"{name}: on the same float32 vertices the exact test agrees on {agree}/{len(sample)}; "
                  f"CPU says hit for {int(verdict['cpu'].sum())}, GPU for {int(verdict['cuda'].sum())}", flush=True)
            print(f"  first: {sample[0]} triangles\n{tri['cpu'][0][0].tolist()}\n{tri['cpu'][1][0].tolist()}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    os.environ.setdefault("WANDB_MODE", "disabled")
    main()
