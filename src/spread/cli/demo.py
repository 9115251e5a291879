"""``python -m spread.cli.demo [--out demo_out]``: the whole loop on one CPU in a few minutes (``make demo``).

1. ``spread-generate``: procedural rooms (at most 16 objects each, so the tiny model learns them quickly);
2. ``spread-train experiment=cpu_hour``: the CPU-hour recipe (tiny base model) for ``--train-minutes``
   (``trainer.max_time``), its cosine learning-rate schedule shortened to ``--train-steps``;
3. ``spread-sample``: one scene per test graph by the recipe's ``sampling`` block (DDIM-50, then ``refine``
   guidance with its weights);
4. ``spread-evaluate`` on the test split (ground truth) and on the samples, with ``--stability-runs``
   physics runs per scene instead of the protocol's 10 (a demo, not a reported number);
5. a table of GRecall, Col_mesh, ASD, Stability, FID and KID: ground truth next to generated. FID and KID
   compare each set's top-down renders with the *validation* rooms' (Inception features), so the ground
   truth column shows the floor that a finite set of true rooms reaches, and the generated column can be
   read against it.

Every stage resumes where it stopped: rooms already written are kept, training continues from
``train/checkpoints/last.ckpt`` (its time budget counts across restarts, so a finished run takes no
more steps), samples and evaluations keep their finished scenes unless the checkpoint changed in this
call (then both start over). ``--fresh`` deletes the output folder first. Each command is printed
before it runs.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

from spread.io import read_json


def columns(metrics: dict) -> list:
    """The table's rows, as the table writer's columns (:mod:`spread.reporting.tables`: display unit, digits, ±):
    every value of the metrics the evaluation selected (Stability's still share too), FID and KID."""
    from spread.reporting.tables import metric_column, set_columns
    from spread.metrics.registry import METRICS, ordered

    names = (metrics.get("protocol") or {}).get("metrics") or [n for n in METRICS.names() if n in metrics]
    values = [v for spec in ordered(METRICS.get(n) for n in names if n in METRICS) for v in spec.values]
    return [metric_column(v) for v in values] + set_columns()


def script(name: str) -> str:
    """A console script of this environment (beside the running interpreter)."""
    return str(Path(sys.executable).parent / name)


def run(*cmd: str) -> None:
    print("\n$ " + " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def file_state(path: Path) -> tuple | None:
    """(size, mtime) of a file, None when it does not exist."""
    return (path.stat().st_size, path.stat().st_mtime_ns) if path.exists() else None


def max_time(minutes: float) -> str:
    """Lightning's ``DD:HH:MM:SS`` for a number of minutes."""
    seconds = max(1, int(round(minutes * 60)))
    return f"00:{seconds // 3600:02d}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def comparison_table(truth: dict, generated: dict, title: str):
    from rich.table import Table

    table = Table(title=title)
    for column in ("metric", "ground truth", "generated"):
        table.add_column(column, justify="left" if column == "metric" else "right")
    for column in columns(generated):
        table.add_row(column.label + column.arrow, *(column.cell(m) for m in (truth, generated)))
    table.add_row("scenes / objects", *(f"{m['n_scenes']} / {m['n_objects']}" for m in (truth, generated)))
    return table


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m spread.cli.demo", description=__doc__.split("\n")[0])
    parser.add_argument("--out", default="demo_out", help="output folder (data/, train/, samples/, eval_*/)")
    parser.add_argument("--rooms", type=int, default=80, help="rooms to generate (10%% go to the test split)")
    parser.add_argument("--max-objects", type=int, default=16, help="objects per room at most")
    parser.add_argument("--train-minutes", type=float, default=4.0, help="training time budget")
    parser.add_argument("--train-steps", type=int, default=800,
                        help="steps the learning-rate schedule decays over (~0.25 s each on one core)")
    parser.add_argument("--stability-runs", type=int, default=2, help="physics runs per scene in evaluation")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fresh", action="store_true", help="delete --out first")
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    from rich.console import Console

    from spread.evaluation.bootstrap import interval_note
    from spread.commands.ablate import recipe_sampling

    args = parse_args(argv)
    out = Path(args.out)
    if args.fresh and out.exists():
        shutil.rmtree(out)
    data, train, samples = out / "data", out / "train", out / "samples"
    run(script("spread-generate"), f"out_dir={data}", f"rooms={args.rooms}", f"seed={args.seed}", "renders=6",
        f"room.max_objects={args.max_objects}", "progress=false")
    ckpt = train / "checkpoints" / "last.ckpt"
    before = file_state(ckpt)
    run(script("spread-train"), "experiment=cpu_hour", f"data.root={data}", f"out_dir={train}", "ckpt_path=last",
        f"trainer.max_time={max_time(args.train_minutes)}", f"trainer.max_steps={args.train_steps}",
        "trainer.check_val_every_n_epoch=25", f"seed={args.seed}", "trainer.enable_progress_bar=false")
    # a checkpoint that changed (training went on) makes earlier samples and their scores stale
    resume = f"resume={str(file_state(ckpt) == before).lower()}"
    sampler, guidance = recipe_sampling("cpu_hour")
    run(script("spread-sample"), f"ckpt={ckpt}", f"data.root={data}", f"out_dir={samples}", *sampler, *guidance,
        f"seed={args.seed}", "batch_size=4", "progress=false", "logger=none", resume)
    evaluate = ["logger=none", f"protocol.stability_runs={args.stability_runs}", "progress=false", "renders=4",
                "reference_split=val"]
    run(script("spread-evaluate"), f"scenes={data / 'test'}", f"reference={data}", f"out_dir={out / 'eval_truth'}",
        *evaluate)
    run(script("spread-evaluate"), f"scenes={samples / 'scenes'}", f"reference={data}",
        f"out_dir={out / 'eval_generated'}", *evaluate, resume)
    truth, generated = (read_json(out / name / "metrics.json")
                        for name in ("eval_truth", "eval_generated"))
    steps = read_json(train / "metrics.json")["global_step"]
    console = Console()
    console.print()
    console.print(comparison_table(truth, generated, f"test split: ground truth vs the cpu_hour recipe "
                                                     f"({steps} steps, DDIM-50 + refine; stability "
                                                     f"{args.stability_runs} runs)"))
    note = interval_note(generated.get("bootstrap"))
    if note:
        console.print(note)
    console.print(f"renders: {data / 'renders'} (rooms), {samples / 'renders'} (ground truth | generated; "
                  f"*_3d.png: 3D view + relation matrix, *_physics.png: before | after physics)", soft_wrap=True)


if __name__ == "__main__":
    main()
