"""Start-up of sweep trials: trial 1 against trials 2..n of one ``spread-sweep`` (Ray Tune, one Ray session,
trials one after another in the re-used trial process), with this checkout's code and, given
``--before-src``, with another checkout's ``src`` (e.g. the commit before :mod:`spread.readonce`).

    .venv/bin/python benchmarks/bench_warm_trials.py --make /tmp/warm          # a dataset and a 2-step checkpoint
    .venv/bin/python benchmarks/bench_warm_trials.py --ckpt CKPT --data DIR [--before-src /tmp/base/src]

Per trial (in the order the trials ran, from each point's ``sampling.json`` time): the trial's seconds (Tune's
row: sampling + evaluation), the sampling **start-up** = ``sampling.json`` seconds − seconds per batch × batches
(checks, graph reads, checkpoint load and hash, model build, renders: none here), the evaluation's seconds, and
the trial process id. Points: ``guidance.collision`` ∈ {0, 0.0025, 0.005, 0.0075} (``--points``), refine
guidance with 2 iterations, DDIM with ``--steps`` steps, Stability 1 run, no FID (``--fid``: with), one torch
thread.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SCRIPTS = Path(sys.executable).parent
#: the tests' shrunken model (tests/helpers.py SMALL_MODEL)
SMALL_MODEL = ["model.config.depth=1", "model.config.dim=32", "model.config.dim_head=8", "model.config.heads=2",
               "model.config.edge_dim=16", "model.config.index_dim=8", "model.config.num_latents=4",
               "model.config.shape_tokens=4", "model.config.shape_dim=16", "model.config.tokenizer_width=16",
               "model.config.tokenizer_points=32", "model.config.num_points=32", "model.config.cond_dim=32"]
COLLISION = ["0.0", "0.0025", "0.005", "0.0075", "0.01", "0.0125"]


def make(root: Path, rooms: int) -> tuple[Path, Path]:
    """A dataset of ``rooms`` generated rooms (30 % test) and a 2-step checkpoint of the shrunken model."""
    from spread.assets.build import build_library
    from spread.configs import compose
    from spread.commands.train import train
    from spread.procgen.dataset import AssetSource, DatasetConfig, generate_dataset
    from spread.procgen.room_types import RoomConfig

    build_library(root / "assets", seed=0, processes=2, progress=False)
    data = root / "data"
    generate_dataset(data, DatasetConfig(rooms=rooms, seed=7, processes=2, renders=0, val_fraction=0.2,
                                         test_fraction=0.3, assets=AssetSource(copy_from=str(root / "assets")),
                                         room=RoomConfig(max_objects=8)), progress=False)
    run = root / "train"
    overrides = [f"data.root={data}", "experiment=quick", *SMALL_MODEL, "trainer.enable_progress_bar=false",
                 "trainer.enable_model_summary=false", "logger=csv", "trainer.num_sanity_val_steps=0",
                 "data.batch_size=4", "trainer.max_steps=2", "trainer.max_time=null"]
    train(compose("train", [f"out_dir={run}", *overrides]), run_dir=run, overrides=overrides)
    return data, run / "checkpoints" / "last.ckpt"


def sweep(ckpt: str, data: str, out: Path, points: int, steps: int, src: str | None, fid: bool) -> float:
    env = {**os.environ, "WANDB_MODE": "disabled", "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "1"}
    if src:
        env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    args = [f"ckpt={ckpt}", f"data.root={data}", "guidance=refine", f"guidance.collision={','.join(COLLISION[:points])}",
            "guidance.gravity=0.001", "guidance.relation=0.001", "guidance.iterations=2", f"sampler.steps={steps}",
            "batch_size=4", "renders=0", "logger=none", "threads=1", "evaluation.protocol.stability_runs=1",
            f"evaluation.fid.enabled={str(fid).lower()}", "max_concurrent=1", "num_cpus=2", f"out_dir={out}"]
    started = time.perf_counter()
    proc = subprocess.run([str(SCRIPTS / "spread-sweep"), *args], env=env, capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(proc.stdout[-2000:] + proc.stderr[-3000:])
    return time.perf_counter() - started


def trials(out: Path) -> list[dict]:
    """One row per point, in the order the trials ran."""
    import csv

    rows = {r["point"]: r for r in csv.DictReader(open(out / "results.csv"))}
    found = []
    for folder in (out / "points").iterdir():
        sampling = json.loads((folder / "sampling.json").read_text())
        metrics = json.loads((folder / "metrics.json").read_text())
        row = rows.get(folder.name, {})
        batches = (sampling.get("seconds_per_batch") or 0) * sampling.get("batches_run", 0)
        found.append({"ran": (folder / "sampling.json").stat().st_mtime, "trial": float(row.get("trial_seconds") or "nan"),
                      "startup": sampling["seconds"] - batches, "evaluation": metrics["run"]["seconds"],
                      "pid": row.get("trial_pid") or "—"})
    return sorted(found, key=lambda r: r["ran"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--make", help="write a dataset and a checkpoint under this folder, print their paths")
    parser.add_argument("--rooms", type=int, default=40)
    parser.add_argument("--ckpt")
    parser.add_argument("--data")
    parser.add_argument("--before-src", help="the src folder of the code to compare with (PYTHONPATH)")
    parser.add_argument("--points", type=int, default=4)
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--fid", action="store_true", help="with FID / KID (Inception features, local weights)")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    if args.make:
        data, ckpt = make(Path(args.make), args.rooms)
        print(f"--data {data} --ckpt {ckpt}")
        return
    root = Path(tempfile.mkdtemp(prefix="bench_warm_"))
    codes = ([("before", args.before_src)] if args.before_src else []) + [("this checkout", None)]
    print(f"load average before: {os.getloadavg()}")
    lines = ["| code | trial | trial s | sampling start-up s | evaluation s | trial pid |", "|---|---:|---:|---:|---:|---|"]
    summary = []
    for label, src in codes:
        wall = sweep(args.ckpt, args.data, root / label.replace(" ", "_"), args.points, args.steps, src, args.fid)
        rows = trials(root / label.replace(" ", "_"))
        for i, r in enumerate(rows, 1):
            lines.append(f"| {label} | {i} | {r['trial']:.1f} | {r['startup']:.2f} | {r['evaluation']:.1f} | {r['pid']} |")
        later = rows[1:]
        summary.append(f"{label}: sweep wall {wall:.1f} s; trial 1 {rows[0]['trial']:.1f} s (start-up "
                       f"{rows[0]['startup']:.2f} s), trials 2..{len(rows)} mean {statistics.mean(r['trial'] for r in later):.1f} s "
                       f"(start-up mean {statistics.mean(r['startup'] for r in later):.2f} s)")
    print("\n".join(lines))
    print("\n".join(summary))
    print(f"load average after: {os.getloadavg()}")


if __name__ == "__main__":
    main()
