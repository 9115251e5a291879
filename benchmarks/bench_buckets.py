"""Object-count-aware batching: training step time with and without ``data.bucket_batches``, one process.

    python benchmarks/bench_buckets.py DATA [--buckets 0 50] [--steps 40] [--rounds 3] [--set OVERRIDE ...]

For each setting, the first ``--steps`` batches of epoch 0 (the cpu_hour recipe's model and batch size unless
``--set`` says otherwise) are trained on one fresh copy of the same model, the settings taking turns for
``--rounds`` rounds so both see the same machine load; prints one table: seconds per step (median over rounds),
the padded object count per batch, the real objects per batch, the padding share, and the speed-up against the
first setting.
"""

from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("data")
    p.add_argument("--buckets", type=int, nargs="+", default=[0, 50])
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--set", nargs="*", default=[], help="extra train overrides (model.penetration_weight=1.0)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    from hydra.utils import instantiate

    from spread.configs import compose

    batches, stats = {}, {}
    for k in args.buckets:
        cfg = compose("train", ["experiment=cpu_hour", f"data.root={args.data}", f"data.bucket_batches={k}", *args.set])
        dm = instantiate(cfg.data)
        dm.setup("fit")
        loader = dm.train_dataloader()
        batches[k] = [b for _, b in zip(range(args.steps), loader)]
        padded = [b["x"].shape[1] for b in batches[k]]
        real = [int(b["mask"].sum()) for b in batches[k]]
        scenes = batches[k][0]["x"].shape[0]
        stats[k] = (statistics.mean(padded), statistics.mean(real) / scenes,
                    1 - sum(real) / sum(b["x"].shape[0] * n for b, n in zip(batches[k], padded)))
    model = instantiate(cfg.model)
    model.set_bounds(dm.translation_bounds())
    times = {k: [] for k in args.buckets}
    for _ in range(args.rounds):
        for k in args.buckets:
            m = copy.deepcopy(model)
            opt = torch.optim.AdamW(m.network.parameters(), lr=1e-4)
            start = time.perf_counter()
            for b in batches[k]:
                loss = m.training_loss(b)
                opt.zero_grad()
                loss.backward()
                opt.step()
            times[k].append((time.perf_counter() - start) / len(batches[k]))
    base = statistics.median(times[args.buckets[0]])
    print(f"| bucket_batches | s/step (median of {args.rounds}) | padded objects / batch | real objects / scene | "
          f"padding share | speed-up |")
    print("|---:|---:|---:|---:|---:|---:|")
    for k in args.buckets:
        t = statistics.median(times[k])
        print(f"| {k} | {t:.3f} | {stats[k][0]:.1f} | {stats[k][1]:.1f} | {stats[k][2]:.2f} | {base / t:.2f}× |")


if __name__ == "__main__":
    main()
