"""``spread-export scenes=DIR format=urdf|mjcf|usd|glb out_dir=OUT``: scene files → simulation-ready files
(:mod:`spread.export`). Exit status 1 when any scene failed."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from spread.cli.errors import command, one_line
from spread.configs import conf_dir, register

register("export")


@command("spread-export", config="export")
@hydra.main(config_path=conf_dir(), config_name="export", version_base="1.3")
@one_line("spread-export")
def main(cfg: DictConfig) -> None:
    from spread.commands.export import export, print_export_summary

    report = export(cfg)
    print_export_summary(report)
    if report.failed:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
