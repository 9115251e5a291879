"""A 3-seed quick ablation (``spread-ablate +preset=quick seeds=[0,1,2]``, every row) on a given dataset with
the tests' shrunken model: wall time with the rows one after another (``stages.max_concurrent=1``) and
concurrent (``=2``), and the table across seeds (mean ± sd across seeds, then ± the bootstrap half-width).

    .venv/bin/python benchmarks/bench_ablate_seeds.py --data DIR [--steps 2] [--concurrent 1,2] [--keep OUT]

Training: the quick preset's recipe with ``tests/helpers.py``'s SMALL_MODEL for ``--steps`` steps per variant
and seed; sampling DDIM-4, refine guidance with 2 iterations; evaluation Stability 1 run, no FID. Each run
starts from an empty folder (nothing re-used); one torch thread in this process.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path


def config(data: str, out: Path, steps: int, concurrent: int):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from helpers import FAST_TRAIN, SMALL_MODEL

    from spread.configs import compose

    cfg = compose("ablate", ["+preset=quick", f"data.root={data}", f"out_dir={out}", "figures=false", "logger=none",
                             "seeds=[0,1,2]", f"stages.max_concurrent={concurrent}"])
    cfg.train.extra = [*SMALL_MODEL, *FAST_TRAIN, f"trainer.max_steps={steps}", "trainer.max_time=null"]
    cfg.sample.extra = ["sampler.steps=4", "progress=false", "renders=0", "figures=0", "batch_size=4",
                        "guidance.iterations=2"]
    cfg.evaluate.extra = ["protocol.stability_runs=1", "fid.enabled=false", "renders=0", "progress=false"]
    return cfg


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True)
    parser.add_argument("--steps", type=int, default=2)
    parser.add_argument("--concurrent", default="1,2", help="stages.max_concurrent values to time, in order")
    parser.add_argument("--keep", default=None, help="keep the last run's folder here (else a temporary one)")
    args = parser.parse_args()
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("WANDB_MODE", "disabled")
    from spread.commands.ablate import ablate

    root = Path(tempfile.mkdtemp(prefix="bench_ablate_"))
    timings, result = [], None
    try:
        for concurrent in [int(c) for c in args.concurrent.split(",")]:
            out = root / f"c{concurrent}"
            started = time.perf_counter()
            result = ablate(config(args.data, out, args.steps, concurrent))
            timings.append((concurrent, time.perf_counter() - started, result.ok))
            table = (out / "ablation.md").read_text()
            if args.keep:
                shutil.copytree(out, Path(args.keep) / f"c{concurrent}", dirs_exist_ok=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    print("\n| stages.max_concurrent | wall (s) | ok |\n|---:|---:|---|")
    for concurrent, seconds, ok in timings:
        print(f"| {concurrent} | {seconds:.1f} | {ok} |")
    print(f"\nload average after the runs: {os.getloadavg()}\n\n{table}")


if __name__ == "__main__":
    main()
