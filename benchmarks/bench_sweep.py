"""A 4-point guidance sweep with spread-sweep (Ray Tune): sequential (max_concurrent=1) against
max_concurrent=2, each from an empty sweep folder, one torch thread per trial; then the re-run of the
finished sweep (every point re-used by fingerprint). Prints one table.

    .venv/bin/python benchmarks/bench_sweep.py --ckpt CKPT --data DIR [--num-cpus 2] [--steps 4] [--cluster]

``--cluster``: instead, the same sweep on a simulated 2-node ``ray.cluster_utils.Cluster`` (1 CPU per node,
``max_concurrent=2``) against 1 node (1 CPU, ``max_concurrent=1``).

Points: guidance.collision ∈ {0, 0.0075} × guidance.gravity ∈ {0.001, 0.004}, refine guidance, DDIM with
``--steps`` steps, Stability 1 run, no FID. Wall seconds include Ray's start and the trials' imports (one Ray
session per sweep, trial processes re-used across trials).
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path


def sweep(ckpt: str, data: str, out: Path, concurrent: int, num_cpus: int, steps: int,
          address: str | None = None) -> tuple[float, int]:
    from spread.commands.in_process import InProcessCommands
    from spread.experiments.sweep import parse_arguments, run_sweep

    where = [f"address={address}"] if address else [f"num_cpus={num_cpus}"]
    plan = parse_arguments([
        f"ckpt={ckpt}", f"data.root={data}", "guidance=refine", "guidance.collision=0.0,0.0075",
        "guidance.gravity=0.001,0.004", "guidance.relation=0.001", f"sampler.steps={steps}", "batch_size=4",
        "renders=0", "logger=none", "threads=1", "evaluation.protocol.stability_runs=1", "evaluation.fid.enabled=false",
        f"max_concurrent={concurrent}", *where, f"out_dir={out}"])
    started = time.perf_counter()
    result = run_sweep(plan, InProcessCommands())
    return time.perf_counter() - started, len(result.rows)


def on_cluster(nodes: int, ckpt: str, data: str, out: Path, steps: int) -> tuple[float, int]:
    """The sweep (max_concurrent = nodes) on a simulated ``ray.cluster_utils.Cluster`` of ``nodes`` nodes of
    one CPU each (all on this machine: a model of a cluster's scheduling, not of its network)."""
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    for _ in range(nodes - 1):
        cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    try:
        return sweep(ckpt, data, out, nodes, 1, steps, address=cluster.address)
    finally:
        ray.shutdown()
        cluster.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--num-cpus", type=int, default=2)
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--cluster", action="store_true",
                        help="instead: a simulated 2-node cluster (1 CPU each) against 1 node")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("WANDB_MODE", "disabled")
    root = Path(tempfile.mkdtemp(prefix="bench_sweep_"))
    rows = []
    try:
        if args.cluster:
            for label, nodes in (("1 node (1 CPU), max_concurrent=1", 1), ("2 nodes (1 CPU each), max_concurrent=2", 2)):
                seconds, n = on_cluster(nodes, args.ckpt, args.data, root / f"n{nodes}", args.steps)
                rows.append((label, n, seconds))
        for label, concurrent in (() if args.cluster else (("sequential (max_concurrent=1)", 1), ("max_concurrent=2", 2))):
            seconds, n = sweep(args.ckpt, args.data, root / f"c{concurrent}", concurrent, args.num_cpus, args.steps)
            rows.append((label, n, seconds))
        if not args.cluster:
            seconds, n = sweep(args.ckpt, args.data, root / "c2", 2, args.num_cpus, args.steps)
            rows.append(("re-run of the finished sweep (re-used)", n, seconds))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    base = rows[0][2]
    print(f"\n| run | points | wall (s) | speed-up vs sequential |\n|---|---:|---:|---:|")
    for label, n, seconds in rows:
        print(f"| {label} | {n} | {seconds:.1f} | {base / seconds:.2f}× |")


if __name__ == "__main__":
    main()
