"""Is the CPU slower than at an older commit? The tiny model's training step, sampling and ``make demo``, old
against new on this machine, runs alternated so both see the same load (issue 29, item 6).

    python benchmarks/cpu_ab.py --old 35871fd [--new HEAD] [--work /tmp/cpu_ab] [--rounds 3] [--demo-rounds 2]
                                [--new-args "model.penetration_weight=0 ..."] [--old-args "..."]

Each commit is cloned from this repository into ``--work`` (``old/``, ``new/``) and installed there with ``make
install``; 80 rooms of at most 16 objects (the demo's) are generated once with the new code. Per round and commit:

* ``train``: ``spread-train experiment=cpu_hour`` for ``--steps`` (30 and 230 by default) with validation, sampling
  during training and logging off; seconds per step = the difference of the two runs' wall times over the difference
  of their steps, so start-up, data loading and the first steps' warm-up cancel. ``--new-args`` / ``--old-args`` are
  extra overrides for one side, to make the two recipes the same work when the recipe changed in between (the
  default ``--new-args`` turns off what issue 33 added to ``cpu_hour`` after 35871fd: the penetration and relation
  terms and size-bucketed batches);
* ``sample``: ``spread-sample`` of the test graphs with the 230-step checkpoint of the same side, DDIM-50 at
  graph_scale 2, unguided, no renders — the whole command's wall time;
* ``demo``: ``python -m spread.cli.demo --fresh`` (``make demo``'s job) — each side's own recipe as a user gets it,
  so this row compares what a user waits for, not equal work.

Prints one table of medians (seconds) and new / old. Wall time of whole processes on a machine others share: read
the ratio, and only within one run.
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ISSUE_33_TERMS = "model.penetration_weight=0 model.spatial_weight=0 data.bucket_batches=0"


def sh(cmd: list[str], cwd: Path, log: Path) -> float:
    """Run ``cmd`` in ``cwd`` with its output in ``log``; its wall time (s). A failure names the log."""
    env = dict(os.environ, WANDB_MODE="disabled", PYTHONUNBUFFERED="1")
    start = time.perf_counter()
    with open(log, "w") as out:
        rc = subprocess.call(cmd, cwd=cwd, stdout=out, stderr=subprocess.STDOUT, env=env)
    if rc:
        sys.exit(f"cpu_ab: {' '.join(cmd[:2])} … failed (exit {rc}); see {log}")
    return time.perf_counter() - start


def checkout(work: Path, side: str, commit: str) -> Path:
    """``work/side``: this repository cloned at ``commit`` and installed (``make install``)."""
    tree = work / side
    if not tree.exists():
        subprocess.check_call(["git", "clone", "-q", str(REPO), str(tree)])
    subprocess.check_call(["git", "-C", str(tree), "fetch", "-q", str(REPO)])  # commits made since the clone
    subprocess.check_call(["git", "-C", str(tree), "checkout", "-q", commit])
    print(f"{side}: {commit} in {tree}, installing …", flush=True)
    sh(["make", "install"], tree, work / f"install_{side}.log")
    return tree


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--old", required=True, help="the older commit (35871fd: before issue 29)")
    ap.add_argument("--new", default="HEAD")
    ap.add_argument("--work", type=Path, default=Path("/tmp/cpu_ab"))
    ap.add_argument("--rounds", type=int, default=3, help="training and sampling rounds (alternated)")
    ap.add_argument("--demo-rounds", type=int, default=2, help="make demo rounds (0: none)")
    ap.add_argument("--steps", type=int, nargs=2, default=[30, 230], metavar=("FEW", "MANY"))
    ap.add_argument("--new-args", default=ISSUE_33_TERMS, help="extra spread-train overrides for the new side")
    ap.add_argument("--old-args", default="", help="extra spread-train overrides for the old side")
    args = ap.parse_args(argv)
    if args.steps[1] <= args.steps[0]:
        ap.error(f"--steps: the second ({args.steps[1]}) must be more than the first ({args.steps[0]})")
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    commits = {side: subprocess.check_output(["git", "-C", str(REPO), "rev-parse", "--short", c], text=True).strip()
               for side, c in (("old", args.old), ("new", args.new))}
    trees = {side: checkout(work, side, commits[side]) for side in ("old", "new")}
    extra = {"old": shlex.split(args.old_args), "new": shlex.split(args.new_args)}
    rooms = work / "rooms"
    if not (rooms / "stats.json").exists():
        sh([str(trees["new"] / ".venv/bin/spread-generate"), f"out_dir={rooms}", "rooms=80", "seed=0", "renders=0",
            "room.max_objects=16", "progress=false"], trees["new"], work / "generate.log")
    times: dict[tuple[str, str], list[float]] = {}

    def train(side: str, steps: int) -> float:
        out = work / f"train_{side}_{steps}"
        shutil.rmtree(out, ignore_errors=True)
        return sh([str(trees[side] / ".venv/bin/spread-train"), "experiment=cpu_hour", f"data.root={rooms}",
                   f"out_dir={out}", f"trainer.max_steps={steps}", "trainer.check_val_every_n_epoch=100000",
                   "model.sample_every_n_epochs=100000", "logger=none", "seed=0", "trainer.enable_progress_bar=false",
                   *extra[side]], trees[side], work / f"train_{side}_{steps}.log")

    few, many = args.steps
    for r in range(args.rounds):
        for side in ("old", "new"):
            per_step = (train(side, many) - train(side, few)) / (many - few)
            times.setdefault(("train s/step", side), []).append(per_step)
            out = work / f"sample_{side}"
            shutil.rmtree(out, ignore_errors=True)
            took = sh([str(trees[side] / ".venv/bin/spread-sample"),
                       f"ckpt={work / f'train_{side}_{many}' / 'checkpoints' / 'last.ckpt'}", f"data.root={rooms}",
                       f"out_dir={out}", "sampler=ddim50", "graph_scale=2.0", "seed=0", "batch_size=4",
                       "progress=false", "logger=none", "renders=0"], trees[side], work / f"sample_{side}.log")
            times.setdefault(("sample (s, whole command)", side), []).append(took)
            print(f"round {r + 1} {side}: {per_step:.4f} s/step, sampling {took:.1f} s", flush=True)
    for r in range(args.demo_rounds):
        for side in ("old", "new"):
            took = sh([str(trees[side] / ".venv/bin/python"), "-m", "spread.cli.demo", "--out",
                       str(work / f"demo_{side}"), "--fresh"], trees[side], work / f"demo_{side}_{r + 1}.log")
            times.setdefault(("make demo (s, own recipe)", side), []).append(took)
            print(f"demo round {r + 1} {side}: {took:.1f} s", flush=True)

    print(f"\nold {commits['old']} against new {commits['new']}, medians of alternated runs "
          f"(new's extra overrides: {args.new_args or 'none'})\n")
    print("| what | old | new | new / old | runs |")
    print("|---|---:|---:|---:|---:|")
    for what in dict.fromkeys(w for w, _ in times):
        old, new = (statistics.median(times[(what, s)]) for s in ("old", "new"))
        print(f"| {what} | {old:.4g} | {new:.4g} | {new / old:.2f} | {len(times[(what, 'old')])} |")


if __name__ == "__main__":
    main()
