"""``spread-import``'s body: a dataset of another layout (3D-FRONT, ...) into the platform's, and its console summary."""

from __future__ import annotations

from omegaconf import DictConfig

from spread.commands.common import record_in_log_folder
from spread.configs import to_object


def import_data(cfg: DictConfig) -> dict:
    """``spread-import``: another layout converted into the dataset folder ``cfg.out_dir``; returns its
    manifest. A missing split file or a bad option raises ``SystemExit`` with one line naming it."""
    from spread.importers.run import import_dataset

    command = to_object(cfg)
    record_in_log_folder(cfg)
    try:
        return import_dataset(command)
    except (FileNotFoundError, ValueError) as exc:
        raise SystemExit(f"spread-import: {exc}") from exc


def print_import_summary(manifest: dict, out_dir: str) -> None:
    from rich.console import Console
    from rich.table import Table

    run = manifest["this_run"]
    table = Table(title=f"imported {manifest['source']['source']} → {out_dir}")
    table.add_column("quantity")
    table.add_column("value", justify="right")
    for split, n in manifest["counts"].items():
        table.add_row(f"rooms ({split})", str(n))
    for room_type, n in manifest["room_types"].items():
        table.add_row(f"rooms of type {room_type}", str(n))
    table.add_row("assets (closed / open meshes / boxes)",
                  f"{manifest['assets']} ({manifest['meshes']['closed']} / {manifest['meshes']['open']} / "
                  f"{manifest['meshes']['boxes']})")
    table.add_row("failed rooms / assets", f"{manifest['failed_rooms']} / {manifest['failed_assets']}")
    agree = manifest["relations_agreement"]
    if agree["spatial_agreement"] is not None:
        table.add_row("file vs platform: spatial codes equal", f"{agree['spatial_agreement']:.3f}")
    if agree["file_support_recall"] is not None:
        table.add_row("file support pairs the platform finds", f"{agree['file_support_recall']:.3f}")
    if manifest["decomposition"]["hausdorff_m"]:
        h = manifest["decomposition"]["hausdorff_m"]
        table.add_row(f"{manifest['decomposition']['method']} Hausdorff median / max (mm)",
                      f"{1000 * h['median']:.1f} / {1000 * h['max']:.1f}")
    table.add_row("assets built this run", str(run["assets_built"]))
    table.add_row("rooms written this run", str(run["rooms_written"]))
    for key in ("assets_per_second", "rooms_per_second"):
        if run.get(key):
            table.add_row(key.replace("_", " "), f"{run[key]:.3f}")
    console = Console()
    console.print(table)
    for err in manifest["errors"]["rooms"][:10]:
        console.print(f"room {err['tag']}: {err['error']}")
    for err in manifest["errors"]["assets"][:10]:
        console.print(f"asset {err.get('asset_id')}: {err['error']}")
    for warning in manifest.get("warnings", []):
        console.print(f"[yellow]warning:[/yellow] {warning}")
