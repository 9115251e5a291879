"""Model hot paths on CPU: training step, share of it in the signed chamfer features, peak memory,
sampling latency.

    python benchmarks/bench_model.py [--batch 4] [--objects 20] [--points 256 1000 2000] [--repeats 2]
                                     [--threads 1]

Prints one table. Scenes are synthetic rooms (6 m × 6 m, boxes of 0.2–1.2 m on the floor, points and
normals sampled on the box surfaces) so that the nearest-neighbour pruning sees realistic layouts;
timesteps are fixed and spread over [0, 1000) so every row sees the same noise levels. Each row runs
in its own process, so "peak RSS" (``resource.ru_maxrss``) is that row's own high-water mark
(torch's CPU allocations are invisible to tracemalloc); "idle RSS" is the process before the first step.

``--threads`` sets torch's intra-op threads (default 1). On a machine whose cores are shared with
other jobs, 2 threads can be 10–25× slower than 1 (OpenMP barriers wait on descheduled threads), so
compare rows only at the same setting and load.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time

BOUNDS = [-3.0, 0.0, -3.0, 3.0, 2.5, 3.0]


def synthetic_batch(B: int, N: int, M: int, seed: int = 0) -> dict:
    import torch

    from spread.data import matrix_to_rot6d, normalize_translation

    g = torch.Generator().manual_seed(seed)
    size = 0.2 + torch.rand(B, N, 3, generator=g)  # box extents, metres
    face = torch.randint(0, 6, (B, N, M), generator=g)
    axis, side = face // 2, (face % 2) * 2 - 1.0
    u = torch.rand(B, N, M, 3, generator=g) - 0.5
    u.scatter_(-1, axis[..., None], (side / 2)[..., None])
    points = u * size[:, :, None, :]
    normals = torch.zeros(B, N, M, 3).scatter_(-1, axis[..., None], side[..., None])
    yaw = torch.rand(B, N, generator=g) * 6.2832
    c, s = yaw.cos(), yaw.sin()
    R = torch.zeros(B, N, 3, 3)
    R[..., 0, 0], R[..., 0, 2], R[..., 1, 1], R[..., 2, 0], R[..., 2, 2] = c, s, 1.0, -s, c
    x_pos, z_pos = torch.rand(2, B, N, generator=g) * 6 - 3
    t = torch.stack([x_pos, size[..., 1] / 2, z_pos], -1)
    x = torch.cat([normalize_translation(t, BOUNDS), matrix_to_rot6d(R)], -1)
    return {"x": x, "mask": torch.ones(B, N, dtype=torch.bool), "points": points, "normals": normals,
            "spatial": torch.randint(0, 7, (B, N, N), generator=g),
            "physical": torch.randint(0, 3, (B, N, N), generator=g)}


def run_row(config: str, variant: str, B: int, N: int, M: int, repeats: int) -> dict:
    """One training-step measurement (in this process)."""
    import torch

    import spread.model.network as network_module
    from spread.model.module import SceneDiffusion

    chamfer_time = [0.0]
    original = network_module.state_distances  # the geometry features' signed distances (the search)

    def timed(*args, **kwargs):
        t0 = time.perf_counter()
        out = original(*args, **kwargs)
        chamfer_time[0] += time.perf_counter() - t0
        return out

    network_module.state_distances = timed
    torch.manual_seed(0)
    from spread.configs import model_config

    model = SceneDiffusion(variant, model_config(config), bounds=BOUNDS)
    opt = model.configure_optimizers()
    batch = synthetic_batch(B, N, M)
    timesteps = torch.linspace(50, 950, B).long()
    idle = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    steps = []
    for i in range(repeats + 1):  # the first is warm-up
        chamfer_time[0] = 0.0
        t0 = time.perf_counter()
        loss = model.training_loss(batch, torch.randn(B, N, 9), timesteps)
        opt.zero_grad()
        loss.backward()
        opt.step()
        model.ema.update(model.network)
        if i:
            steps.append((time.perf_counter() - t0, chamfer_time[0]))
    step = sorted(steps)[len(steps) // 2]
    return {"config": config, "variant": variant, "M": M, "step_s": step[0], "chamfer_share": step[1] / step[0],
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "idle_mb": idle,
            "params_m": sum(p.numel() for p in model.network.parameters()) / 1e6}


def run_sampling(B: int, N: int, M: int, sampler: str, variant: str) -> dict:
    import torch

    from spread.model.module import SceneDiffusion

    torch.manual_seed(0)
    from spread.configs import model_config

    model = SceneDiffusion(variant, model_config("tiny"), bounds=BOUNDS).eval()
    batch = synthetic_batch(B, N, M)
    t0 = time.perf_counter()
    model.sample(batch, sampler, generator=torch.Generator().manual_seed(0))
    wall = time.perf_counter() - t0
    return {"sampler": sampler, "variant": variant, "M": M, "per_scene_s": wall / B, "batch_s": wall,
            "peak_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def in_subprocess(kind: str, threads: int, **kwargs) -> dict:
    job = {"kind": kind, "threads": threads, **kwargs}
    out = subprocess.run([sys.executable, __file__, "--child", json.dumps(job)],
                         capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"{kind} {kwargs} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--objects", type=int, default=20)
    ap.add_argument("--points", type=int, nargs="+", default=[256, 1000, 2000])
    ap.add_argument("--configs", nargs="+", default=["tiny", "paper"])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--sampler", default="ddim-50")
    ap.add_argument("--sample-points", type=int, default=256)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        import torch

        job = json.loads(args.child)
        kind = job.pop("kind")
        torch.set_num_threads(job.pop("threads"))
        print(json.dumps(run_row(**job) if kind == "train" else run_sampling(**job)))
        return

    import torch

    B, N = args.batch, args.objects
    rows = []
    for config in args.configs:
        rows.append(in_subprocess("train", args.threads, config=config, variant="base", B=B, N=N, M=args.points[0],
                                  repeats=args.repeats))
        for M in args.points:
            rows.append(in_subprocess("train", args.threads, config=config, variant="geometry", B=B, N=N, M=M,
                                      repeats=args.repeats))
    samples = [in_subprocess("sample", args.threads, B=B, N=N, M=args.sample_points, sampler=args.sampler, variant=v)
               for v in ("base", "geometry")]

    print(f"# bench_model  {time.strftime('%Y-%m-%d')}  {platform.processor() or platform.machine()}  "
          f"{os.cpu_count()} cores, torch {torch.__version__}, {args.threads} thread(s), "
          f"load avg {os.getloadavg()[0]:.1f}  batch {B} scenes × {N} objects")
    print("| what | config | variant | M | params (M) | time (s) | chamfer share | peak RSS (MB) | idle RSS (MB) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| train step | {r['config']} | {r['variant']} | {r['M']} | {r['params_m']:.1f} | {r['step_s']:.2f} | "
              f"{100 * r['chamfer_share']:.0f} % | {r['peak_mb']:.0f} | {r['idle_mb']:.0f} |")
    for s in samples:
        print(f"| sample {s['sampler']} per scene | tiny | {s['variant']} | {s['M']} |  | {s['per_scene_s']:.2f} "
              f"(batch {s['batch_s']:.1f}) |  | {s['peak_mb']:.0f} |  |")


if __name__ == "__main__":
    main()
