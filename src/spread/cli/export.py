"""``spread-export scenes=DIR format=urdf|mjcf|usd|glb out_dir=OUT``: scene files → simulation-ready files
(:mod:`spread.export`). Exit status 1 when any scene failed."""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main


@console_main("spread-export", config="export")
def main(cfg: DictConfig) -> None:
    from spread.commands.export import export, print_export_summary

    report = export(cfg)
    print_export_summary(report)
    if report.failed:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
