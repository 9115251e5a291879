"""``spread-generate``'s body: procedural rooms into a dataset folder, and its console summary."""

from __future__ import annotations

from omegaconf import DictConfig

from spread.commands.common import record_in_log_folder
from spread.configs import to_object


def generate(cfg: DictConfig) -> dict:
    """``spread-generate``: the dataset folder ``cfg.out_dir``; returns its manifest."""
    from pathlib import Path

    from spread.io import run_lock
    from spread.procgen.dataset import check_config, check_places, generate_dataset

    command = to_object(cfg)
    check_places(Path(command.out_dir), command)  # before the log and the lock: a refusal leaves nothing
    check_config(command)  # settings too (``processes=0``, ``room.room_types.kitchen=inf``); its warnings come later
    with run_lock(command.out_dir, "spread-generate"):  # a second run on the folder is refused, never mixed
        record_in_log_folder(cfg)
        return generate_dataset(command.out_dir, command, progress=command.progress)


def print_dataset_summary(manifest: dict, out_dir: str) -> None:
    from rich.console import Console
    from rich.table import Table

    stats = manifest["statistics"]
    run = manifest["this_run"]
    table = Table(title=f"dataset {out_dir}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for split, n in manifest["counts"].items():
        table.add_row(f"rooms ({split})", str(n))
    opr = stats["objects_per_room"]
    table.add_row("objects per room min / mean / max", f"{opr['min']} / {opr['mean']:.1f} / {opr['max']}")
    table.add_row("support pairs per room (mean)", f"{stats['support_pairs_per_room']['mean']:.1f}")
    table.add_row("share of supported objects that are stacked", f"{stats['share_stacked']:.3f}")
    table.add_row("categories in use / in library", f"{len(stats['categories'])} / {len(manifest['categories'])}")
    table.add_row("asset library (s)", f"{run['seconds_assets']:.1f}")
    table.add_row("rooms generated this run", str(run["rooms_generated"]))
    table.add_row("room generation (s)", f"{run['seconds_rooms']:.1f}")
    if run["rooms_per_second"]:
        table.add_row("rooms per second", f"{run['rooms_per_second']:.2f}")
    table.add_row("failed rooms", str(len(manifest["failed_rooms"])))
    Console().print(table)
    top = sorted(stats["categories"].items(), key=lambda kv: -kv[1])[:12]
    Console().print("most frequent categories: " + ", ".join(f"{k} {v}" for k, v in top))
    for message in manifest.get("warnings") or []:
        Console().print(f"[yellow]warning: {message}[/yellow]")
