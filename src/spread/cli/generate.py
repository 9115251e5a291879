"""``spread-generate out_dir=DIR rooms=N seed=S``: procedural rooms → dataset folder (:mod:`spread.procgen`)."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from spread.cli.errors import command, one_line
from spread.configs import conf_dir, register

register("generate")


@command("spread-generate", config="generate")
@hydra.main(config_path=conf_dir(), config_name="generate", version_base="1.3")
@one_line("spread-generate")
def main(cfg: DictConfig) -> None:
    from spread.commands.generate import generate, print_dataset_summary

    print_dataset_summary(generate(cfg), cfg.out_dir)


if __name__ == "__main__":
    main()
