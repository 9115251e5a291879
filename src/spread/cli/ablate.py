"""``spread-ablate +preset=quick``: train / sample / evaluate base, geometry and guidance → the ablation table.

The work is :func:`spread.commands.ablate.ablate`. Exit status 1 when a stage failed (the table
is still written, with the failed rows empty).
"""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main
from spread.configs import register

register()


@console_main("spread-ablate", config="ablate")
def main(cfg: DictConfig) -> None:
    from spread.commands.ablate import ablate, print_ablation

    result = ablate(cfg)
    print_ablation(result, cfg)
    if not result.ok:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
