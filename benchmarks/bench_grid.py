"""The 27-point ``+sweep=guidance_grid`` before and after ``spread-sweep``: Hydra multirun (``spread-sample -m``,
the basic launcher, one point after another in one process) against ``spread-sweep max_concurrent=2`` (Ray Tune
trials), each from an empty folder, with the same fast settings. Prints one table.

    .venv/bin/python benchmarks/bench_grid.py --ckpt CKPT --data DIR [--steps 4] [--only before|after]

Settings of every point: refine guidance over the preset's 3 × 3 × 3 weights, DDIM ``--steps``, batch 4,
in-process sampling (``workers=0``), one torch thread, Stability 1 run, no FID, no renders or figures, no
logger. Wall seconds are the whole command's (processes started here, Ray start and imports included).
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def fast(steps: int) -> list[str]:
    return [f"sampler.steps={steps}", "batch_size=4", "workers=0", "threads=1", "renders=0", "figures=0",
            "logger=none", "progress=false", "evaluation.protocol.stability_runs=1", "evaluation.fid.enabled=false",
            "evaluation.renders=0"]


def timed(cmd: list[str]) -> float:
    started = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1",
                                                                    "WANDB_MODE": "disabled"})
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} exited with {proc.returncode}:\n{(proc.stdout + proc.stderr)[-3000:]}")
    return time.perf_counter() - started


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ckpt", required=True)
    parser.add_argument("--data", required=True)
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--only", choices=("before", "after"), default=None)
    args = parser.parse_args()
    bin_dir = Path(sys.executable).parent
    common = ["+sweep=guidance_grid", f"ckpt={args.ckpt}", f"data.root={args.data}", *fast(args.steps)]
    root = Path(tempfile.mkdtemp(prefix="bench_grid_"))
    rows = []
    try:
        if args.only in (None, "before"):
            folder = root / "multirun"
            seconds = timed([str(bin_dir / "spread-sample"), "-m", *common, f"sweep_dir={folder}"])
            rows.append(("Hydra multirun (`spread-sample -m`, basic launcher)",
                         len(list(folder.glob("c*/metrics.json"))), seconds))
        if args.only in (None, "after"):
            folder = root / "tune"
            seconds = timed([str(bin_dir / "spread-sweep"), *common, "max_concurrent=2", "num_cpus=2",
                             f"out_dir={folder}"])
            rows.append(("`spread-sweep max_concurrent=2` (Ray Tune)", len(list(folder.glob("points/*/metrics.json"))),
                         seconds))
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print("\n| run | points | wall (s) | s per point |\n|---|---:|---:|---:|")
    for label, n, seconds in rows:
        print(f"| {label} | {n} | {seconds:.1f} | {seconds / max(n, 1):.1f} |")
    print(f"\nload average after the runs: {os.getloadavg()}")


if __name__ == "__main__":
    main()
