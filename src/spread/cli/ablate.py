"""``spread-ablate +preset=quick``: train / sample / evaluate base, geometry and guidance → the ablation table.

The work is :func:`spread.commands.ablate.ablate`. Exit status 1 when a stage failed (the table
is still written, with the failed rows empty).
"""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from spread.cli.errors import command, one_line
from spread.configs import conf_dir, register

register()


@command("spread-ablate", config="ablate")
@hydra.main(config_path=conf_dir(), config_name="ablate", version_base="1.3")
@one_line("spread-ablate")
def main(cfg: DictConfig) -> None:
    from spread.commands.ablate import ablate, print_ablation

    result = ablate(cfg)
    print_ablation(result, cfg)
    if not result.ok:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
