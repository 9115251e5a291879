"""``spread-export``'s body: generated scenes into another layout (SceneEval, meshes), and its console summary."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from spread.commands.common import record_config
from spread.configs import to_object


def export(cfg: DictConfig):
    """``spread-export``: every scene of ``cfg.scenes`` as simulation-ready files in ``cfg.out_dir``; returns the
    :class:`~spread.export.ExportReport`. Bad options raise ``SystemExit`` with one line naming them."""
    from spread.export import FORMATS, assets_of, export_folder

    command = to_object(cfg)
    if command.format not in FORMATS:
        raise SystemExit(f"spread-export: format={command.format}: unknown (known: {', '.join(FORMATS)})")
    if not Path(command.scenes).is_dir():
        raise SystemExit(f"spread-export: scenes={command.scenes}: not a folder")
    try:
        assets = assets_of(command.scenes, command.assets)
    except FileNotFoundError as exc:
        raise SystemExit(f"spread-export: {exc}") from exc
    from spread.io import check_folder_kind

    check_folder_kind(command.out_dir, "spread-export", {"export"})  # a dataset's or a run's folder: refused whole
    record_config(cfg, command.out_dir)()
    return export_folder(command.scenes, assets, command.out_dir, command.format, floor=command.floor,
                         progress=command.progress)


def print_export_summary(report) -> None:
    print(f"spread-export: {len(report.written)} scenes written as {report.format} to {report.out_dir}, "
          f"{len(report.failed)} failed (see export.json)")
    for scene_id, error in list(report.failed.items())[:10]:
        print(f"  failed {scene_id}: {error}")
    for file, note in list(getattr(report, "duplicates", {}).items())[:10]:
        print(f"  duplicate id in {file}: {note}")
