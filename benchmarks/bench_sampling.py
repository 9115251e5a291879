"""Sampling latency per scene, batched, for each sampler: what ``spread-sample`` spends per batch.

    python benchmarks/bench_sampling.py --data DATASET [--ckpt TINY.ckpt] [--batch 8]
        [--samplers ddpm-1000 ddim-100 ddim-50 dpmsolver++-20] [--paper-sampler ddim-50] [--threads 1]
        [--geometry-scale 2.0 --graph-scale 2.0]

Scenes are the first ``--batch`` graphs of ``DATASET/test`` (repeated when the split has fewer), encoded
and collated exactly as ``spread-sample`` does (:class:`spread.sampling.worker.SampleWorker`), and sampled
in one batch with the EMA weights; file writing is not timed. The tiny geometry model is ``--ckpt``
(a ``spread-train experiment=quick`` checkpoint) or, without it, a freshly initialised one; the paper
row is a freshly initialised paper-sized geometry model (M = 2,000 points): the work per step does not
depend on the weights, except that the signed chamfer pruning sees the sampled layouts, which an
untrained model makes denser. ``--geometry-scale S`` (a geometry checkpoint) adds, per sampler, the rows at
classifier-free guidance on the geometry features (``geometry_scale``, with ``--graph-scale``'s graph guidance): the
geometry-blind features made once per sample (the platform's way) and made again at every step (as before stop 53),
alternated three times, medians. Prints one markdown table.
"""

from __future__ import annotations

import argparse
import os
import platform
import time


def test_batch(data: str, batch: int, num_points: int, seed: int, geometry_distance: str = "chamfer") -> dict:
    from spread.data import SceneDataset, collate_scenes

    dataset = SceneDataset(data, "test", num_points=num_points, seed=seed, geometry_distance=geometry_distance)
    return collate_scenes([dataset[i % len(dataset)] for i in range(batch)])


def tiny_model(ckpt: str | None, data: str):
    from spread.data import load_stats
    from spread.model.module import SceneDiffusion

    if ckpt:
        return SceneDiffusion.load_from_checkpoint(ckpt, map_location="cpu").eval()
    bounds = load_stats(os.path.join(data, "stats.json"))["bounds_translations"]
    from spread.configs import model_config

    return SceneDiffusion("geometry", model_config("tiny"), bounds=bounds).eval()


def time_sampler(model, batch: dict, sampler: str) -> float:
    import torch

    t0 = time.perf_counter()
    model.sample(batch, sampler, generator=torch.Generator().manual_seed(0))
    return time.perf_counter() - t0


def time_scaled(model, batch: dict, sampler: str, geometry_scale: float, graph_scale: float, once: bool) -> float:
    """Seconds for one batch with ``geometry_scale`` (the blind features made ``once`` or at every step)."""
    import torch

    import spread.model.network as network_module
    from spread.model.diffusion import denoise

    keep = network_module.reusable
    if not once:
        network_module.reusable = lambda: False
    try:
        t0 = time.perf_counter()
        with torch.no_grad():
            problem = model.denoising(batch, graph_scale=graph_scale, geometry_scale=geometry_scale)
            denoise(problem, sampler, torch.Generator().manual_seed(0))
        return time.perf_counter() - t0
    finally:
        network_module.reusable = keep


def scaled_rows(name: str, model, batch: dict, sampler: str, geometry_scale: float, graph_scale: float) -> list[str]:
    from spread.model import Sampler

    steps = Sampler.from_config(sampler).num_steps
    B = batch["mask"].shape[0]
    walls = {True: [], False: []}
    for _ in range(3):
        for once in (True, False):
            walls[once].append(time_scaled(model, batch, sampler, geometry_scale, graph_scale, once))
    out = []
    for once in (True, False):
        wall = sorted(walls[once])[1]
        how = "blind features once" if once else "blind features every step"
        out.append(f"| {name}, geometry_scale={geometry_scale} graph_scale={graph_scale}, {how} | "
                   f"{sum(p.numel() for p in model.network.parameters()) / 1e6:.1f} | {batch['points'].shape[2]} | "
                   f"{sampler} | {steps} | {B} | {wall:.1f} | {wall / B:.2f} | {1000 * wall / steps:.0f} |")
    return out


def row(name: str, model, batch: dict, sampler: str) -> str:
    from spread.model import Sampler

    steps = Sampler.from_config(sampler).num_steps
    wall = time_sampler(model, batch, sampler)
    B = batch["mask"].shape[0]
    params = sum(p.numel() for p in model.network.parameters()) / 1e6
    return (f"| {name} | {params:.1f} | {batch['points'].shape[2]} | {sampler} | {steps} | {B} | {wall:.1f} | "
            f"{wall / B:.2f} | {1000 * wall / steps:.0f} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", required=True, help="dataset folder (its test split is sampled)")
    ap.add_argument("--ckpt", default=None, help="tiny geometry checkpoint (default: untrained tiny model)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--samplers", nargs="+", default=["ddpm-1000", "ddim-100", "ddim-50", "dpmsolver++-20"])
    ap.add_argument("--paper-sampler", default="ddim-50", help="sampler of the paper-sized row ('' to skip)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--geometry-scale", type=float, default=None,
                    help="also time sampling at this geometry_scale (a geometry model), blind features once vs per step")
    ap.add_argument("--graph-scale", type=float, default=1.0, help="graph_scale of the --geometry-scale rows")
    args = ap.parse_args()

    import torch

    from spread.model.module import SceneDiffusion
    from spread.sampling.worker import checkpoint_data_settings

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    tiny = tiny_model(args.ckpt, args.data)
    data = {"num_points": tiny.config.num_points, "seed": 0}
    if args.ckpt:
        from spread.safe_load import load_checkpoint

        data = checkpoint_data_settings(load_checkpoint(args.ckpt), tiny)  # weights only: no code runs
    batch = test_batch(args.data, args.batch, data["num_points"], data["seed"], data.get("geometry_distance", "chamfer"))
    objects = batch["num_objects"].float()
    print(f"# bench_sampling  {time.strftime('%Y-%m-%d')}  {platform.machine()}  {os.cpu_count()} cores, "
          f"torch {torch.__version__}, {args.threads} thread(s), load avg {os.getloadavg()[0]:.1f}; batch of "
          f"{args.batch} test scenes of {args.data} ({objects.mean():.1f} objects mean, {int(objects.max())} max)")
    print("| model | params (M) | M | sampler | steps | batch | batch (s) | per scene (s) | per step (ms) |")
    print("|---|---|---|---|---|---|---|---|---|")
    name = "tiny geometry" + (" (trained)" if args.ckpt else " (untrained)")
    for sampler in args.samplers:
        print(row(name, tiny, batch, sampler), flush=True)
        if args.geometry_scale is not None:
            for line in scaled_rows(name, tiny, batch, sampler, args.geometry_scale, args.graph_scale):
                print(line, flush=True)
    if args.paper_sampler:
        from spread.configs import model_config

        paper = SceneDiffusion("geometry", model_config("paper"), bounds=tiny.hparams.bounds).eval()
        big = test_batch(args.data, args.batch, paper.config.num_points, data["seed"])
        print(row("paper geometry (untrained)", paper, big, args.paper_sampler), flush=True)


if __name__ == "__main__":
    main()
