"""``spread-train experiment=NAME data.root=DIR``: train one variant with Lightning (:mod:`spread.training`;
the command is :func:`spread.commands.train.train`)."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

from spread.cli.errors import command, one_line
from spread.configs import conf_dir, register

register()


@command("spread-train", config="train")
@hydra.main(config_path=conf_dir(), config_name="train", version_base="1.3")
@one_line("spread-train")
def main(cfg: DictConfig) -> None:
    from spread.commands.train import train

    train(cfg)


if __name__ == "__main__":
    main()
