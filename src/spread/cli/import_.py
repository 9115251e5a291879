"""``spread-import source=spread_release|threed_front src=DIR out_dir=DIR``: another layout → dataset folder.

The work is :func:`spread.importers.run.import_dataset`; this file turns the Hydra config into its
arguments and prints a summary (``import`` is a Python keyword, hence the module name).
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from spread.cli import conf_dir


def import_config(cfg: DictConfig):
    """The :class:`~spread.importers.run.ImportConfig` of a composed ``conf/import.yaml``."""
    from spread.importers.run import ImportConfig

    def opt(key):
        value = cfg.get(key)
        return None if value in (None, "") else str(value)

    return ImportConfig(
        source=str(cfg.source), src=str(cfg.src), out_dir=str(cfg.out_dir), splits=opt("splits"),
        room_type=opt("room_type"), future_models=opt("future_models"), val_fraction=float(cfg.val_fraction),
        processes=int(cfg.processes), progress=bool(cfg.progress), stats=str(cfg.stats), renders=int(cfg.renders),
        decomposition=str(cfg.decomposition),
        decomposition_settings=OmegaConf.to_container(cfg.decomposition_settings, resolve=True) or {},
        density=float(cfg.density), fidelity_samples=int(cfg.fidelity_samples),
    )


def print_summary(manifest: dict, out_dir: str) -> None:
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


@hydra.main(config_path=conf_dir(), config_name="import", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from spread.importers.run import import_dataset

    try:
        manifest = import_dataset(import_config(cfg))
    except (FileNotFoundError, ValueError) as exc:  # a missing split file, bad options: one clear line
        raise SystemExit(f"spread-import: {exc}") from exc
    print_summary(manifest, cfg.out_dir)


if __name__ == "__main__":
    main()
