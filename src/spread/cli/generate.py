"""``spread-generate out_dir=DIR rooms=N seed=S``: procedural rooms → dataset folder."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig, OmegaConf

from spread.cli import conf_dir


def dataset_config(cfg: DictConfig):
    from spread.procgen.dataset import DatasetConfig
    from spread.procgen.room_types import RoomConfig
    from spread.procgen.settle import SettleConfig

    room = OmegaConf.to_container(cfg.room, resolve=True)
    settle = OmegaConf.to_container(cfg.settle, resolve=True)
    try:
        return DatasetConfig(
            rooms=int(cfg.rooms), seed=int(cfg.seed), processes=int(cfg.processes),
            val_fraction=float(cfg.val_fraction), test_fraction=float(cfg.test_fraction),
            max_attempts=int(cfg.max_attempts), renders=int(cfg.renders),
            asset_seed=int(cfg.assets.seed), asset_variants=int(cfg.assets.variants),
            asset_categories=list(cfg.assets.categories) if cfg.assets.categories else None,
            assets_from=cfg.assets.get("from") or None,
            room=RoomConfig(**room), settle=SettleConfig(**settle),
        )
    except TypeError as exc:  # an unknown key under room/settle
        raise SystemExit(f"spread-generate: bad config: {exc}") from exc


def print_summary(manifest: dict, out_dir: str) -> None:
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


@hydra.main(config_path=conf_dir(), config_name="generate", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from spread.procgen.dataset import generate_dataset

    manifest = generate_dataset(cfg.out_dir, dataset_config(cfg), progress=bool(cfg.progress))
    print_summary(manifest, cfg.out_dir)


if __name__ == "__main__":
    main()
