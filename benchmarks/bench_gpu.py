"""The paper-size model on a GPU: kernel launches per step (always, on CPU) and, where CUDA is present, training
s/step, sampling s/scene and the nearest-point kernel. One table. Fits a short GPU slot (docs/gpu.md: what a bare
GPU machine lacks and how to carry it).

    python benchmarks/bench_gpu.py                       # counts on CPU; + every CUDA row when a GPU is there
    python benchmarks/bench_gpu.py --data ROOMS          # + the guided pipeline rows (a dataset folder: meshes)
    python benchmarks/bench_gpu.py --quick               # small sizes (a CPU check of the script itself)
    python benchmarks/bench_gpu.py --skip-counts --json out.json

Rows:

* **ops / …** — kernel operators (:mod:`spread.model.opcount`: every dispatched ATen operator that computes, views
  and metadata left out; a custom operator such as the dense nearest search counts once: its CUDA implementation is
  one kernel) of the paper config (``ModelConfig()``, M = 2,000, ``nearest=dense``) at batch 16 × 20 objects, CPU
  tensors, as CUDA runs them (the perceiver's point tokens padded to 112 channels, which CPU tensors are not): one
  denoising step (the network call with the batch's condition made once per sample; and with the
  sampler's update), one training step (loss forward + backward), base and +Geometry; the +Geometry denoising step
  at 10 and 40 objects (growth). ``syncs``: host reads of tensor values inside the network call.
* **gflop / …** — the same denoising and training steps' floating-point operations (GFLOP per step of 16 scenes,
  ``torch.utils.flop_counter``: matmuls and attention, forward and backward; elementwise work and the nearest
  search's custom operator not included): what the steps cost when a GPU is busy computing rather than launching —
  the ratio no launch-count work can go below.
* **train s/step** — CUDA, paper size, batch 16 × 20 × 2,000 synthetic rooms (6 m square, boxes with surface samples)
  already on the device, bf16 autocast, fused AdamW, gradient clipping at 1 and the EMA update, as ``spread-train``
  runs them (Lightning's own overhead and data loading not included); median of timed steps after warm-up.
* **nearest** — the dense search kernel and the pruned search against exact brute force (torch on the GPU) at B = 2
  (largest distance difference, points off by more than 1 µm), then ms per call at B = 16 and 64.
* **sample s/scene** — CUDA, DDIM-50 at batch 64 synthetic rooms: eager float32, CUDA graph float32, CUDA graph bf16;
  with ``--data``: the platform's ``ScenePipeline`` on the dataset's graphs (repeated to 128, batched 64 at a time
  as ``spread-sample`` batches them: sorted by object count) with the release's recipe (DDPM-1000 + ``guidance=refine``,
  100 iterations, paper weights; estimated as 10 × DDPM-100 + 100/3 × three refine iterations) and the paper's
  (``guidance=paper``), CUDA graph + bf16; DDPM once more in the earlier slots' layout (one batch of every size);
  the refine row once more with ``guidance.detect=host`` (python-fcl and scipy on host copies, against the default's
  search on the GPU). The network has random weights (paper size, untrained): samples
  interpenetrate more than a trained model's, so the guidance rows are an upper bound of its collision work.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))

BOUNDS = [-3.0, 0.0, -3.0, 3.0, 2.5, 3.0]


def synthetic_batch(B: int, N: int, M: int, seed: int = 0, device="cpu") -> dict:
    """B rooms of N boxes (0.2–1.2 m) on a 6 m floor, M surface samples each (bench_model's rooms), each object's
    points in Morton order as a dataset gives them (spread.data.points)."""
    from bench_model import synthetic_batch as rooms

    from spread.data.points import morton_order

    batch = rooms(B, N, M, seed)
    order = morton_order(batch["points"])[..., None].expand(-1, -1, -1, 3)
    batch["points"], batch["normals"] = batch["points"].gather(2, order), batch["normals"].gather(2, order)
    return {k: v.to(device) for k, v in batch.items()}


def model(variant: str, M: int, device="cpu", nearest: str = "dense", **overrides):
    import torch

    from spread.model import ModelConfig
    from spread.model.module import SceneDiffusion

    torch.manual_seed(0)
    return SceneDiffusion(variant, ModelConfig(num_points=M, nearest=nearest, **overrides), bounds=BOUNDS).to(device)


def untrained_but_live(m):
    """``m`` with its zero-initialised layers (the head, AdaLN and geometry modulations) drawn small and random: an
    initialised network predicts ε̂ = 0 exactly, which makes any comparison of sampled states (CUDA graph against
    eager, bf16 against float32) vacuous; the kernels run are the same."""
    import torch

    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in m.parameters():
            if not p.any():
                p.copy_(0.02 * torch.randn(p.shape, generator=g).to(p))
    return m


# ---- kernel operators (CPU) ---------------------------------------------------------------------------------------
def counts(B: int, N: int, M: int, quick: bool) -> dict:
    import torch

    from torch.utils.flop_counter import FlopCounterMode

    import spread.model.perceiver as perceiver
    from spread.model import Sampler
    from spread.model.diffusion import reverse_process
    from spread.model.opcount import OperatorCounter

    perceiver.token_multiple = lambda device: perceiver.CHANNEL_MULTIPLE  # CUDA's tokens (the CPU's are unpadded)
    perceiver.cross_mode = lambda device: "formed"  # CUDA's cross-attentions (the CPU's are absorbed)
    out = {}
    for variant in ("base", "geometry"):
        m = model(variant, M)
        net = m.ema.module.eval()
        batch = synthetic_batch(B, N, M)
        t = torch.full((B,), 500)
        with torch.no_grad():
            cond = net.condition(batch)
            net(batch["x"], t, cond)  # warm (first-call setup)
            with OperatorCounter() as c, FlopCounterMode(display=False) as f:
                net(batch["x"], t, cond)
        out[f"ops/denoise/{variant}"], out[f"syncs/denoise/{variant}"] = c.total, c.syncs
        out[f"gflop/denoise/{variant}"] = round(f.get_total_flops() / 1e9, 1)
        # a whole step of the sampling loop: the network call + the sampler's update (DDIM, averaged over 5 steps)
        sampler = Sampler("ddim", 5)
        calls = {"n": 0}

        def eps_fn(x, tt):
            calls["n"] += 1
            return net(x, tt, cond)

        with torch.no_grad(), OperatorCounter() as c2:
            reverse_process(sampler, eps_fn, batch["mask"],
                            generator=[torch.Generator().manual_seed(i) for i in range(B)])
        out[f"ops/sampling_step/{variant}"] = round(c2.total / calls["n"], 1)
        m.train()
        timesteps = torch.linspace(50, 950, B).long()

        def train_step():
            loss = m.training_loss(batch, timesteps=timesteps)
            loss.backward()
            m.zero_grad(set_to_none=True)  # (no kernel: the optimiser's zero_grad, outside the count's operators)

        train_step()
        with OperatorCounter() as c3, FlopCounterMode(display=False) as f3:
            train_step()
        out[f"ops/train/{variant}"] = c3.total
        out[f"gflop/train/{variant}"] = round(f3.get_total_flops() / 1e9, 1)
        print(f"  counted {variant}", flush=True)
    for kind in ("denoise", "sampling_step", "train"):
        out[f"ops/{kind}/ratio"] = round(out[f"ops/{kind}/geometry"] / out[f"ops/{kind}/base"], 3)
    for kind in ("denoise", "train"):
        out[f"gflop/{kind}/ratio"] = round(out[f"gflop/{kind}/geometry"] / out[f"gflop/{kind}/base"], 2)
    for n in ((4, 8) if quick else (10, 40)):
        net = model("geometry", M).ema.module.eval()
        batch = synthetic_batch(B if not quick else 2, n, M)
        with torch.no_grad():
            cond = net.condition(batch)
            with OperatorCounter() as c:
                net(batch["x"], torch.full((batch["x"].shape[0],), 500), cond)
        out[f"ops/denoise/geometry/{n}_objects"] = c.total
    return out


# ---- CUDA ---------------------------------------------------------------------------------------------------------
def cuda_time(fn, warmup: int, steps: int) -> tuple[float, list[float]]:
    """Median seconds of ``fn()`` over ``steps`` timed calls after ``warmup``; all times."""
    import torch

    sync = torch.cuda.synchronize if torch.cuda.is_available() else (lambda: None)
    for _ in range(warmup):
        fn()
    sync()
    times = []
    for _ in range(steps):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times


def train_rows(B: int, N: int, M: int, steps: int, compile_step: bool, profile: bool = False,
               pruned: bool = False, mode: str | None = None, variants=("base", "geometry"),
               profile_out: Path | None = None) -> dict:
    """``mode``: torch.compile's mode for the compiled step (``reduce-overhead``: CUDA graphs); ``profile``: the top
    CUDA kernels of one step printed (8 rows), or appended to ``profile_out`` (30 rows, headed by the row's name).
    A variant ``geometry:absorbed`` is +Geometry with the perceiver's cross-attentions absorbed (CUDA's default is
    ``formed``: :func:`spread.model.perceiver.cross_mode`), to time both ways on one GPU."""
    import torch

    import spread.model.perceiver as perceiver

    out = {}
    rows = [(v, "dense") for v in variants] + ([("geometry", "pruned")] if pruned else [])
    device_mode = perceiver.cross_mode
    for variant, nearest in rows:
        variant, _, cross = variant.partition(":")
        perceiver.cross_mode = (lambda device, cross=cross: cross) if cross else device_mode
        m = model(variant, M, "cuda", nearest=nearest)
        m.train()
        batch = synthetic_batch(B, N, M, device="cuda")
        params = [p for p in m.network.parameters() if p.requires_grad]
        opt = torch.optim.AdamW(params, lr=1e-4, weight_decay=1e-4, fused=True)
        loss_fn = torch.compile(m.training_loss, mode=mode) if compile_step else m.training_loss

        def step():
            with torch.autocast("cuda", dtype=torch.bfloat16):
                loss = loss_fn(batch)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 1.0, foreach=True)
            opt.step()
            opt.zero_grad(set_to_none=True)
            m.ema.update(m.network)

        torch.cuda.reset_peak_memory_stats()
        n = steps if nearest == "dense" else max(2, steps // 4)
        median, _ = cuda_time(step, 3, n)
        name = variant + (f" ({cross})" if cross else "") + ("" if nearest == "dense" else " (pruned search)") \
            + (" compiled" if compile_step else "") + (f" {mode}" if compile_step and mode else "")
        if profile and profile_out is not None:
            with open(profile_out, "a") as f:
                f.write(f"## train {name}: B={B} N={N} M={M}, {median:.4f} s/step\n{profile_step(step, 30)}\n\n")
        elif profile:
            print(profile_step(step), flush=True)
        out[f"train/{name}/s_per_step"] = round(median, 4)
        out[f"train/{name}/peak_GiB"] = round(torch.cuda.max_memory_allocated() / 2 ** 30, 2)
        print(f"  train {name}: {median:.4f} s/step", flush=True)
        del m, opt, batch
        torch.cuda.empty_cache()
    perceiver.cross_mode = device_mode
    tag = (" compiled" if compile_step else "") + (f" {mode}" if compile_step and mode else "")
    for geometry in ("geometry", "geometry (absorbed)"):
        if f"train/base{tag}/s_per_step" in out and f"train/{geometry}{tag}/s_per_step" in out:
            out[f"train{tag}/ratio" + ("" if geometry == "geometry" else " (absorbed)")] = round(
                out[f"train/{geometry}{tag}/s_per_step"] / out[f"train/base{tag}/s_per_step"], 3)
    return out


def nearest_rows(N: int, M: int) -> dict:
    """Each CUDA kernel and the pruned search against exact brute force (torch, on the GPU) at B = 2, then times."""
    import torch

    from spread.model.geometry import prepare_points
    from spread.model.nearest import nearest_other_point
    from spread.model.nearest_dense import _brute_force, nearest_dense_search
    from spread.model.poses import pose_points, poses_from_state

    out = {}

    def posed(B):
        batch = synthetic_batch(B, N, M, seed=3, device="cuda")
        cloud = prepare_points(batch["points"], batch["normals"], batch["mask"], morton=True)
        t, R = poses_from_state(batch["x"], torch.tensor(BOUNDS, device="cuda"))
        return pose_points(cloud.points, t, R), cloud, t, R, batch["mask"]

    def dist(world, index):
        flat = world.reshape(world.shape[0], -1, 3)
        return (flat - flat.gather(1, index[..., None].expand(-1, -1, 3))).norm(dim=-1)

    world, cloud, t, R, mask = posed(2)
    vp = mask[:, :, None].expand(-1, -1, M).reshape(2, -1)
    reference = dist(world, _brute_force(world.reshape(2, -1, 3), vp, M))
    searches = {"kernel": lambda w: nearest_dense_search(w, mask),
                "pruned": lambda w: nearest_other_point(w, cloud.points, t, R, mask)}
    for name, search in searches.items():
        d = dist(world, search(world))
        out[f"nearest/{name}/max_diff_vs_brute_force"] = float((d - reference).abs().max())
        out[f"nearest/{name}/points_off_by_1e-6"] = int(((d - reference).abs() > 1e-6).sum())
    for B in (16, 64):
        world, cloud, t, R, mask = posed(B)
        for name, search in searches.items():
            if B == 64 and name != "kernel":
                continue
            ms, _ = cuda_time(lambda: search(world), 1, 3 if name != "pruned" else 1)
            out[f"nearest/B{B}/{name}_ms"] = round(ms * 1000, 2)
    out |= kernel_rows(N, M)
    print("  " + ", ".join(f"{k}={v}" for k, v in out.items()), flush=True)
    return out


def kernel_rows(N: int, M: int, device: str = "cuda", sizes: tuple = (4, 64)) -> dict:
    """The two Triton kernels of the step's geometry features (``spread::pose_states``, ``spread::signed_nearest``)
    against their torch paths on the same GPU at B = 4 (largest differences: metres), and ms per call at B = 64;
    ``broken``: kernels Triton could not build or run here (the torch path ran instead, with a warning)."""
    import torch

    from spread.model import nearest_dense as nd
    from spread.model.geometry import prepare_points
    from spread.model.poses import denormalize_affine

    out = {}
    for B in sizes:
        batch = synthetic_batch(B, N, M, seed=5, device=device)
        cloud = prepare_points(batch["points"], batch["normals"], batch["mask"], morton=True)
        offset, scale = denormalize_affine(torch.tensor(BOUNDS, device=device))
        x = batch["x"].float()

        def kernels():
            world, normals, boxes = torch.ops.spread.pose_states(x, offset, scale, cloud.points, cloud.normals,
                                                                 nd.BLOCK_K)
            return (world, normals, boxes), torch.ops.spread.signed_nearest(world, normals, boxes, cloud.valid,
                                                                             cloud.no_neighbour)

        if B == sizes[0]:
            (world, normals, boxes), (index, dist) = kernels()
            tw, tn, tb = nd.pose_torch(x, offset, scale, cloud.points.float(), cloud.normals.float(), nd.BLOCK_K)
            out["kernels/pose_max_diff_m"] = float(max((world - tw).abs().max(), (boxes - tb).abs().max()))
            out["kernels/pose_normals_max_diff"] = float((normals - tn).abs().max())
            flat = world.reshape(B, -1, 3)  # exact reference: brute force (torch's CPU path prunes, inexact)
            vp = cloud.valid[:, :, None].expand(-1, -1, M).reshape(B, -1)
            ref = nd._brute_force(flat, vp, M, max_elements=1 << 28)
            ref_d = nd.sign_distances(flat, normals.reshape(B, -1, 3), ref, cloud.valid, M, float(cloud.no_neighbour))
            out["kernels/signed_nearest_max_diff_m"] = float((dist - ref_d).abs().max())
            out["kernels/signed_nearest_points_off_1e-5"] = int(((dist - ref_d).abs() > 1e-5).sum())
        else:
            ms, _ = cuda_time(kernels, 1, 5)
            out[f"kernels/B{B}/pose+signed_nearest_ms"] = round(ms * 1000, 2)
    out["kernels/broken"] = sorted(nd._BROKEN) or "none"
    return out


def profile_step(step, rows: int = 8) -> str:
    """The top ``rows`` CUDA kernels of one call of ``step`` (torch.profiler), one line each."""
    import torch
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        step()
        torch.cuda.synchronize()
    return prof.key_averages().table(sort_by="self_cuda_time_total", row_limit=rows, max_name_column_width=50)


def sample_rows(B: int, N: int, M: int, steps: int) -> dict:
    import torch

    from spread.model import Sampler
    from spread.model.diffusion import denoise
    from spread.sampling.pipeline import ScenePipeline

    out = {}
    m = untrained_but_live(model("geometry", M, "cuda")).eval()
    batch = synthetic_batch(B, N, M, device="cuda")
    sampler = Sampler("ddim", steps)
    states = {}
    for name, graph, precision in (("eager fp32", False, "32"), ("graph fp32", True, "32"), ("graph bf16", True, "bf16")):
        pipe = ScenePipeline(m, None, sampler, cuda_graph=graph, precision=precision)
        with torch.no_grad():
            problem = pipe.on_device(m.denoising(batch))

        def run():
            gens = [torch.Generator().manual_seed(i) for i in range(B)]
            return denoise(problem, sampler, gens)

        median, _ = cuda_time(run, 1, 1)
        states[name] = run()
        out[f"sample/ddim{steps}/{name}/s_per_scene"] = round(median / B, 4)
        print(f"  DDIM-{steps} {name}: {median / B:.4f} s/scene ({median:.2f} s per batch of {B})", flush=True)
        if name == "graph bf16":  # no step may read the device on the host: count the reads, say where they are
            import warnings

            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                torch.cuda.set_sync_debug_mode("warn")
                try:
                    run()
                finally:
                    torch.cuda.set_sync_debug_mode(0)
            reads = [w for w in caught if "synchroniz" in str(w.message)]
            out["sample/host_syncs_in_loop"] = len(reads)
            where = {}
            for w in reads:
                site = f"{Path(w.filename).name}:{w.lineno}"
                where[site] = where.get(site, 0) + 1
            if where:
                out["sample/host_sync_sites"] = where
    out["sample/graph_vs_eager_max_diff"] = float((states["graph fp32"] - states["eager fp32"]).abs().max())
    out["sample/bf16_vs_fp32_max_diff"] = float((states["graph bf16"] - states["eager fp32"]).abs().max())
    return out


def sample_profile_rows(B: int, N: int, M: int, profile_out: Path | None) -> dict:
    """The top 30 CUDA kernels of two eager bf16 denoising steps (DDIM-2, batch ``B`` synthetic rooms, +Geometry at
    paper size: where a sampling step's GPU time goes), appended to ``profile_out`` (printed when None)."""
    import torch

    from spread.model import Sampler
    from spread.model.diffusion import denoise
    from spread.sampling.pipeline import ScenePipeline

    m = untrained_but_live(model("geometry", M, "cuda")).eval()
    sampler = Sampler("ddim", 2)
    pipe = ScenePipeline(m, None, sampler, cuda_graph=False, precision="bf16")
    with torch.no_grad():
        problem = pipe.on_device(m.denoising(synthetic_batch(B, N, M, device="cuda")))

    def step():
        return denoise(problem, sampler, [torch.Generator().manual_seed(i) for i in range(B)])

    median, _ = cuda_time(step, 1, 3)
    head = f"## sample ddim-2 eager bf16: B={B} N={N} M={M}, {median / 2:.4f} s per denoising step"
    text = f"{head}\n{profile_step(step, 30)}"
    if profile_out is not None:
        with open(profile_out, "a") as f:
            f.write(text + "\n\n")
    else:
        print(text, flush=True)
    print(f"  sample ddim-2 eager bf16: {median / 2:.4f} s per denoising step at batch {B}", flush=True)
    return {"sample_profile/eager bf16/s_per_step": round(median / 2, 4)}


def platform_batches(scenes: list, B: int) -> list[list]:
    """``scenes`` in the batches ``spread-sample`` makes of them (:func:`spread.sampling.plan.plan_batches`: sorted by
    object count, then ``B`` at a time, so each batch is padded to its own largest scene only); a repeated scene counts
    as one more graph."""
    from spread.sampling.plan import Graph, plan_batches

    graphs = [Graph(f"{i:06d}", "", s.num_objects) for i, s in enumerate(scenes)]
    return [[scenes[int(item.graph.scene_id)] for item in plan.items] for plan in plan_batches(graphs, 1, B, 0)]


def padded_share(batches: list[list]) -> float:
    """The share of the batches' object slots that are padding (each batch padded to its largest scene)."""
    real = sum(s.num_objects for b in batches for s in b)
    slots = sum(len(b) * max(s.num_objects for s in b) for b in batches)
    return 1.0 - real / slots


class Oracle:
    """A stand-in for a trained network in the guided pipeline: ε̂ that denoises to the batch's own states (the rooms'
    poses, each real object's translation moved by a fixed draw of ``jitter`` metres per axis, as a trained model's
    sample is near a plausible room but not collision-free): ``ε̂(x_t, t) = (x_t − √ᾱ_t·x_0)/√(1 − ᾱ_t)``. The untrained
    network's samples are degenerate (every object near the same place: 1.6 M colliding triangle pairs in 6 refine
    iterations at the fifth slot), which is not what the guidance meets after a trained model; with the oracle the
    refine iterations see room-like poses (each t = 0 projection returns to them, then one guidance step). Everything
    else is the model's (``__getattr__``); its network is not called."""

    def __init__(self, model, jitter: float, seed: int = 0):
        self.model, self.jitter, self.seed = model, float(jitter), seed

    def __getattr__(self, name):
        return getattr(self.model, name)

    def denoising(self, batch: dict, use_ema: bool = True, graph_scale: float = 1.0, **extra):
        import dataclasses

        import torch

        problem = self.model.denoising(batch, use_ema, graph_scale, **extra)
        device = problem.mask.device
        x0 = batch["x"].to(device).float().clone()
        g = torch.Generator().manual_seed(self.seed)
        scale = (self.model.bounds[3:] - self.model.bounds[:3]).to(device).float() / 2  # metres per normalised unit
        shift = (self.jitter * torch.randn(x0.shape[:-1] + (3,), generator=g)).to(device) / scale
        x0[..., :3] += shift * problem.mask[..., None].to(x0.dtype)
        abar = self.model.alphas_cumprod.to(device).float()

        def eps_fn(x, t):
            a = abar[t].view(-1, 1, 1)
            return (x - a.sqrt() * x0) / (1 - a).sqrt()

        return dataclasses.replace(problem, eps_fn=eps_fn)


def pipeline_rows(data: Path, B: int, quick: bool) -> dict:
    """The platform's ``ScenePipeline`` on the dataset's rooms, repeated to 2·B scenes and batched as ``spread-sample``
    batches them (sorted by object count: :func:`platform_batches`), CUDA graph + bf16. DDPM's per-step work does not
    depend on its number of steps, so DDPM-1000 is estimated as 10 × DDPM-100; the refine iterations are measured on
    a DDIM-2 sample and scaled to 100. One row more in the earlier slots' layout (``mixed``: one batch of the first B
    scenes, every size padded to the largest room), for comparison with their figures. Then the guidance after
    trained-like samples (:class:`Oracle`: the rooms' poses jittered by 3 cm, and exactly), its cost per iteration, and
    the recipe estimated from it: the untrained network's degenerate poses are the guidance's worst case, not its
    use."""
    import torch

    from spread.assets.library import AssetLibrary
    from spread.data import SceneDataset
    from spread.data.stats import load_stats
    from spread.model import ModelConfig
    from spread.model.module import SceneDiffusion
    from spread.sampling.pipeline import ScenePipeline
    from spread.scene import read_scene

    out = {}
    library = AssetLibrary.load(data / "assets")
    M = 2000 if not quick else 64
    files = [f for split in ("test", "val", "train") for f in sorted((data / split).glob("*.npz"))]
    dataset = SceneDataset(data, "test", library=library, num_points=M)  # the encoder (graphs, points)
    rooms = [read_scene(f, assets=library) for f in files[:2 * B]]
    scenes = [rooms[i % len(rooms)] for i in range(2 * B)]
    layouts = {"sorted": platform_batches(scenes, B), "mixed": [scenes[:B]]}
    for layout, batches in layouts.items():
        out[f"pipeline/{layout}/padded_share"] = round(padded_share(batches), 3)
        out[f"pipeline/{layout}/batch_objects"] = [[min(s.num_objects for s in b), max(s.num_objects for s in b)]
                                                   for b in batches]
    print(f"  {len(rooms)} rooms → {2 * B} scenes; padded object slots: "
          + ", ".join(f"{k} {out[f'pipeline/{k}/padded_share']:.0%} {out[f'pipeline/{k}/batch_objects']}"
                      for k in layouts), flush=True)
    torch.manual_seed(0)
    config = ModelConfig(num_points=M) if not quick else ModelConfig(num_points=M, dim=64, depth=2, num_latents=16)
    m = SceneDiffusion("geometry", config, bounds=load_stats(data / "stats.json")["bounds_translations"])
    m = m.to("cuda" if torch.cuda.is_available() else "cpu").eval()
    refine_iterations = 3
    ddpm_steps = 10 if quick else 100
    recipes = [("sorted", f"ddim2+refine{refine_iterations}", "ddim-2",
                {"mode": "refine", "iterations": refine_iterations}),
               # the same with the guidance's geometry found on the host (python-fcl, scipy), as before the device path
               ("sorted", f"ddim2+refine{refine_iterations} detect=host", "ddim-2",
                {"mode": "refine", "iterations": refine_iterations, "detect": "host"}),
               ("sorted", "ddim3+paper", "ddim-3", {"mode": "paper"}),
               ("sorted", f"ddpm{ddpm_steps} unguided", f"ddpm-{ddpm_steps}", {"mode": "none"}),
               ("mixed", f"ddpm{ddpm_steps} unguided", f"ddpm-{ddpm_steps}", {"mode": "none"})]
    # the guidance after a trained-like sample (Oracle): the rooms' poses jittered by 3 cm, and exactly
    oracle_iterations = 10
    oracles = {"oracle 3cm": Oracle(m, 0.03), "oracle 0cm": Oracle(m, 0.0)}
    recipes += [("sorted", "oracle 3cm ddim2 unguided", "ddim-2", {"mode": "none"}),
                ("sorted", f"oracle 3cm ddim2+refine{oracle_iterations}", "ddim-2",
                 {"mode": "refine", "iterations": oracle_iterations}),
                ("sorted", f"oracle 0cm ddim2+refine{oracle_iterations}", "ddim-2",
                 {"mode": "refine", "iterations": oracle_iterations})]

    def run(batches, sampler, guidance, name: str = "") -> tuple[float, dict]:
        model = oracles[" ".join(name.split()[:2])] if name.startswith("oracle") else m
        pipe = ScenePipeline(model, dataset, sampler, guidance, cuda_graph=True, precision="bf16")
        seconds, totals = 0.0, {}
        for batch in batches:
            gens = [torch.Generator().manual_seed(i) for i in range(len(batch))]
            t0 = time.perf_counter()
            pipe(batch, gens)
            if torch.cuda.is_available():
                torch.cuda.synchronize()
            seconds += time.perf_counter() - t0
            for k, v in (pipe.guidance_stats or {}).items():
                totals[k] = totals.get(k, 0) + v if isinstance(v, (int, float)) else v
        return seconds, totals

    for batches in layouts.values():  # warm-up, untimed: the kernels and each batch size's CUDA graph are built
        run(batches, "ddim-2", recipes[0][3])
    for layout, name, sampler, guidance in recipes:
        batches = layouts[layout]
        n = sum(len(b) for b in batches)
        seconds, stats = run(batches, sampler, guidance, name)
        key = f"pipeline/{layout}/{name}"
        out[f"{key}/s_per_scene"] = round(seconds / n, 4)
        if stats:
            out[f"{key}/guidance"] = {k: round(v, 2) if isinstance(v, float) else v for k, v in stats.items()}
        print(f"  {layout} {name}: {seconds / n:.4f} s/scene ({seconds:.1f} s for {n} scenes in {len(batches)} "
              f"batches); guidance {stats}", flush=True)
    scale = 1000 // ddpm_steps
    for layout in layouts:
        out[f"pipeline/{layout}/ddpm1000 unguided (estimate: {scale} × ddpm{ddpm_steps})/s_per_scene"] = round(
            scale * out[f"pipeline/{layout}/ddpm{ddpm_steps} unguided/s_per_scene"], 4)
    refine = out[f"pipeline/sorted/ddim2+refine{refine_iterations}/s_per_scene"]
    out["pipeline/sorted/ddpm1000+refine100 (estimate)/s_per_scene"] = round(
        scale * out[f"pipeline/sorted/ddpm{ddpm_steps} unguided/s_per_scene"] + refine * 100 / refine_iterations, 3)
    # trained-like: 1,100 network steps (1,000 + one per refine iteration) + 100 of the oracle's guidance iterations
    network_step = scale * out[f"pipeline/sorted/ddpm{ddpm_steps} unguided/s_per_scene"] / 1000
    guidance = (out[f"pipeline/sorted/oracle 3cm ddim2+refine{oracle_iterations}/s_per_scene"]
                - out["pipeline/sorted/oracle 3cm ddim2 unguided/s_per_scene"]) / oracle_iterations
    out["pipeline/sorted/guidance iteration, oracle 3cm/s_per_scene"] = round(guidance, 5)
    out["pipeline/sorted/ddpm1000+refine100 (estimate, trained-like: 1,100 network steps + 100 oracle 3cm guidance "
        "iterations)/s_per_scene"] = round(1100 * network_step + 100 * guidance, 3)
    return out


def graph_rows(data: Path, quick: bool) -> dict:
    """``sampling.cuda_graph`` at its default (null: the step recorded where the model says it reads nothing on the
    host) against eager (``false``), for each model that samples through the one loop — SPREAD base and +Geometry,
    DiffuScene, InstructScene (small initialised networks, weights drawn small and random so the states move; the
    dataset's first 16 training rooms): the same states, how many graphs were recorded, and the seconds of a DDIM-20
    batch after a warm one. On the CPU both ways run eagerly (a check of the script)."""
    import torch

    from spread.data import SceneDataModule
    from spread.data.stats import load_stats
    from spread.methods.base import dataset_facts
    from spread.methods.diffuscene import DiffuScene
    from spread.methods.instructscene import InstructScene
    from spread.model import ModelConfig
    from spread.model.diffusion import denoise
    from spread.model.module import SceneDiffusion
    from spread.sampling.pipeline import ScenePipeline

    device = "cuda" if torch.cuda.is_available() else "cpu"
    M = 64 if quick else 256
    dm = SceneDataModule(data, batch_size=4 if quick else 16, num_points=M)
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    B = batch["x"].shape[0]
    facts = dataset_facts(data)
    config = ModelConfig(num_points=M, dim=64, depth=2, num_latents=16)
    bounds = load_stats(data / "stats.json")["bounds_translations"]
    torch.manual_seed(0)
    models = {"spread base": SceneDiffusion("base", config, bounds=bounds),
              "spread geometry": SceneDiffusion("geometry", config, bounds=bounds),
              "diffuscene": DiffuScene("tiny", **facts), "instructscene": InstructScene("tiny", **facts)}
    out = {}
    for name, model in models.items():
        model = untrained_but_live(model).to(device).eval()
        if getattr(model, "ema", None) is not None:  # sampling reads the EMA's weights
            with torch.no_grad():
                for p, q in zip(model.ema.module.parameters(), model.network.parameters()):
                    p.copy_(q)
        states, seconds = {}, {}
        for setting in (None, False):
            pipe = ScenePipeline(model, None, "ddim-20", cuda_graph=setting)
            with torch.no_grad():
                problem = pipe.on_device(model.denoising(batch))

            def run():
                return denoise(problem, pipe.sampler, [torch.Generator().manual_seed(i) for i in range(B)])

            run()  # warm: kernels built, the graph recorded
            if device == "cuda":
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            states[setting] = run()
            if device == "cuda":
                torch.cuda.synchronize()
            seconds[setting] = time.perf_counter() - t0
            if setting is None:
                out[f"graphs/{name}/recorded_by_default"] = bool(pipe.cuda_graph and device == "cuda")
                out[f"graphs/{name}/graphs_recorded"] = int(getattr(problem.eps_fn, "captures", 0))
        out[f"graphs/{name}/max_diff_default_vs_eager"] = float((states[None] - states[False]).abs().max())
        out[f"graphs/{name}/states_move"] = float(states[False].abs().max())
        out[f"graphs/{name}/s_per_batch_default_eager"] = [round(seconds[None], 4), round(seconds[False], 4)]
        print(f"  {name}: recorded {out[f'graphs/{name}/recorded_by_default']}, "
              f"max diff {out[f'graphs/{name}/max_diff_default_vs_eager']:.2e}, "
              f"s per DDIM-20 batch of {B} {seconds[None]:.4f} (default) / {seconds[False]:.4f} (eager)", flush=True)
    return out


def table(results: dict) -> str:
    lines = ["| measurement | value |", "|---|---|"]
    for key, value in results.items():
        lines.append(f"| {key} | {value} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes: a check of the script itself")
    ap.add_argument("--data", type=Path, help="a dataset folder: adds the guided pipeline rows")
    ap.add_argument("--skip-counts", action="store_true")
    ap.add_argument("--only", nargs="*", default=None,
                    help="parts: train nearest sample compile pipeline graphs sample_profile (the last two only "
                         "when named; pipeline and graphs need --data)")
    ap.add_argument("--compile", action="store_true", help="also a torch.compile'd training step")
    ap.add_argument("--profile", action="store_true", help="print the top CUDA kernels of one training step")
    ap.add_argument("--profile-out", type=Path, default=None,
                    help="with --profile: append 30 kernel rows per training row (eager and compiled) to this file")
    ap.add_argument("--compile-mode", default=None, help="torch.compile mode of the compiled step (reduce-overhead)")
    ap.add_argument("--variants", nargs="*", default=["base", "geometry"],
                    help="variants of the training rows (geometry:absorbed: the perceiver's absorbed cross-attention)")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--threads", type=int, default=None)
    args = ap.parse_args()

    import torch

    if args.threads:
        torch.set_num_threads(args.threads)
    B, N, M = (2, 6, 64) if args.quick else (16, 20, 2000)
    results = {"date": time.strftime("%Y-%m-%d"), "machine": platform.node(), "torch": torch.__version__,
               "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None}
    t_start = time.perf_counter()
    if not args.skip_counts:
        print("operator counts (CPU tensors) ...", flush=True)
        results |= counts(B, N, M, args.quick)
    parts = args.only or ["train", "nearest", "sample", "pipeline"]
    if args.compile and "compile" not in parts:
        parts = [*parts, "compile"]

    def save() -> None:  # after every part: a slot that ends early still returns what was measured
        results["bench_seconds"] = round(time.perf_counter() - t_start, 1)
        if args.json:
            args.json.write_text(json.dumps(results, indent=1, default=str))

    steps = 4 if args.quick else 10
    if torch.cuda.is_available():
        torch.backends.cuda.matmul.allow_tf32 = False  # float32 means float32 (the kernel's comparisons too)
        cuda_parts = {"train": lambda: train_rows(B, N, M, steps, False, profile=args.profile,
                                                  profile_out=args.profile_out, variants=args.variants),
                      "nearest": lambda: nearest_rows(N, M),
                      "sample": lambda: sample_rows(4 if args.quick else 64, N, M, 5 if args.quick else 50),
                      "compile": lambda: train_rows(B, N, M, steps, True, mode=args.compile_mode,
                                                    variants=args.variants, profile=args.profile,
                                                    profile_out=args.profile_out),
                      "sample_profile": lambda: sample_profile_rows(4 if args.quick else 64, N, M, args.profile_out)}
        # the compiled step last: it compiles for minutes
        for part in ("train", "nearest", "sample", "sample_profile", "compile"):
            if part in parts:
                results |= cuda_parts[part]()
                save()
    if args.data is not None and "graphs" in parts:
        results |= graph_rows(args.data, args.quick)
        save()
    if args.data is not None and "pipeline" in parts:
        results |= pipeline_rows(args.data, 4 if args.quick else 64, args.quick)
    save()
    print(table(results))


if __name__ == "__main__":
    os.environ.setdefault("WANDB_MODE", "disabled")
    main()
