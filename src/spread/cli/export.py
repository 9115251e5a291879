"""``spread-export scenes=DIR format=urdf|mjcf|usd|glb out_dir=OUT``: scene files → simulation-ready files.

The work is :func:`spread.export.export_folder` (formats and layout in :mod:`spread.export`); this file turns
the Hydra config into its arguments and prints a summary. Exits with status 1 when any scene failed.
"""

from __future__ import annotations

from pathlib import Path

import hydra
from omegaconf import DictConfig

from spread.cli import conf_dir


def assets_of(scenes: str, assets: str | None) -> Path:
    """The asset library folder: ``assets`` if given, else ``assets/`` beside the scenes folder or inside it."""
    if assets:
        path = Path(assets)
        if not (path / "index.json").exists():
            raise SystemExit(f"spread-export: assets={assets}: not an asset library (no index.json)")
        return path
    for candidate in (Path(scenes).parent / "assets", Path(scenes) / "assets"):
        if (candidate / "index.json").exists():
            return candidate
    raise SystemExit(f"spread-export: no asset library beside scenes={scenes} (looked for ../assets and assets/); "
                     "give assets=DIR")


@hydra.main(config_path=conf_dir(), config_name="export", version_base="1.3")
def main(cfg: DictConfig) -> None:
    from spread.export import FORMATS, export_folder

    fmt = str(cfg.format)
    if fmt not in FORMATS:
        raise SystemExit(f"spread-export: format={fmt}: unknown (known: {', '.join(FORMATS)})")
    if not Path(str(cfg.scenes)).is_dir():
        raise SystemExit(f"spread-export: scenes={cfg.scenes}: not a folder")
    report = export_folder(str(cfg.scenes), assets_of(str(cfg.scenes), cfg.assets), str(cfg.out_dir), fmt,
                           floor=bool(cfg.floor), progress=bool(cfg.progress))
    print(f"spread-export: {len(report.written)} scenes written as {fmt} to {report.out_dir}, "
          f"{len(report.failed)} failed (see export.json)")
    for scene_id, error in list(report.failed.items())[:10]:
        print(f"  failed {scene_id}: {error}")
    if report.failed:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
