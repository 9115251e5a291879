"""Where a training step's CPU time goes, on real batches of a dataset: per part of the model (forward of
each top-level module, backward, optimiser, EMA, data loading) and torch's top operators.

    python benchmarks/profile_step.py DATASET [--variant geometry] [--batch 8] [--steps 20] [--threads 1]
                                      [--model tiny] [--set key=value ...] [--ops 15]

Runs ``--steps`` optimiser steps of ``SceneDiffusion`` (after 3 warm-up steps) on the train split of DATASET,
as Lightning would (AdamW, gradient clipping at 1, EMA update), timing each phase with ``perf_counter``; the
forward pass is split by module with forward hooks (nested modules are charged to their top-level part:
shape encoder, edge encoder, perceiver, denoiser, chamfer features). ``--set`` changes SceneDiffusion
arguments (``prediction=sample``) or, as ``config.X=V``, the network (``config.depth=4``). Prints one table,
then torch.profiler's operators by self CPU time over 5 steps.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict


def parse_value(text: str):
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return {"true": True, "false": False, "none": None}.get(text.lower(), text)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dataset")
    ap.add_argument("--variant", default="geometry")
    ap.add_argument("--model", default="tiny")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--ops", type=int, default=15)
    ap.add_argument("--augment", action="store_true")
    ap.add_argument("--no-dedupe", action="store_true", help="encode every object's shape (drop shape_index)")
    ap.add_argument("--no-cache", action="store_true", help="re-read every scene file")
    ap.add_argument("--set", nargs="*", default=[])
    args = ap.parse_args()

    import torch

    import spread.model.network as network_module
    from spread.configs import model_config
    from spread.data import SceneDataModule
    from spread.model import SceneDiffusion

    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    config_fields, module_args = {}, {}
    for item in args.set:
        key, _, value = item.partition("=")
        if key.startswith("config."):
            config_fields[key[len("config."):]] = parse_value(value)
        else:
            module_args[key] = parse_value(value)
    cfg = model_config(args.model, **config_fields)
    dm = SceneDataModule(args.dataset, batch_size=args.batch, num_points=cfg.num_points, seed=0, augment=args.augment,
                         cache=not args.no_cache)
    model = SceneDiffusion(args.variant, cfg, bounds=dm.translation_bounds(), **module_args)
    model.train()
    opt = torch.optim.AdamW(model.network.parameters(), lr=1e-4, weight_decay=1e-4)

    times: dict[str, float] = defaultdict(float)
    stack: list[tuple[str, float]] = []
    parts = {"shape encoder": model.network.shape_encoder, "edge encoder": model.network.edge_encoder,
             "denoiser": model.network.denoiser}
    if model.network.perceiver is not None:
        parts["perceiver"] = model.network.perceiver
    for name, module in parts.items():
        module.register_forward_pre_hook(lambda m, a, name=name: stack.append((name, time.perf_counter())))
        module.register_forward_hook(lambda m, a, o: times.__setitem__(stack[-1][0], times[stack[-1][0]]
                                                                         + time.perf_counter() - stack.pop()[1]))
    original = network_module.state_distances  # the per-step signed chamfer search (the network's name for it)

    def timed_chamfer(*a, **k):
        t0 = time.perf_counter()
        out = original(*a, **k)
        times["chamfer features"] += time.perf_counter() - t0
        return out

    network_module.state_distances = timed_chamfer
    loader = iter(dm.train_dataloader())
    objects = 0

    def step(record: bool) -> None:
        nonlocal objects
        t0 = time.perf_counter()
        batch = next(loader)
        if args.no_dedupe:
            batch.pop("shape_index", None)
        t1 = time.perf_counter()
        loss = model.training_loss(batch)
        t2 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        t3 = time.perf_counter()
        torch.nn.utils.clip_grad_norm_(model.network.parameters(), 1.0)
        opt.step()
        t4 = time.perf_counter()
        model.ema.update(model.network)
        t5 = time.perf_counter()
        if record:
            objects += int(batch["mask"].sum())
            for name, dt in (("data", t1 - t0), ("forward (all)", t2 - t1), ("backward", t3 - t2),
                             ("clip + AdamW", t4 - t3), ("EMA", t5 - t4), ("step", t5 - t0)):
                times[name] += dt

    for _ in range(3):
        step(False)
    if not args.no_cache:  # the cache is warm after the first epoch: measure that state
        data = dm.dataset("train")
        for i in range(len(data)):
            data.read(i)
    times.clear()
    for _ in range(args.steps):
        step(True)
    n = args.steps
    total = times["step"]
    print(f"# profile_step {time.strftime('%Y-%m-%d %H:%M')} {args.model} {args.variant} batch {args.batch} "
          f"threads {args.threads} steps {n} objects/batch {objects / n:.1f} set {args.set}"
          f"{' no-dedupe' if args.no_dedupe else ''}{' no-cache' if args.no_cache else ''}")
    print("| part | ms / step | share |")
    print("|---|---:|---:|")
    order = ["data", "forward (all)", "shape encoder", "edge encoder", "chamfer features", "perceiver", "denoiser",
             "backward", "clip + AdamW", "EMA", "step"]
    for name in order:
        if name in times:
            print(f"| {name} | {1000 * times[name] / n:.1f} | {times[name] / total:.0%} |")
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(5):
            step(False)
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=args.ops))


if __name__ == "__main__":
    main()
