"""``spread-train experiment=NAME data.root=DIR``: train one variant with Lightning (:mod:`spread.training`;
the command is :func:`spread.commands.train.train`)."""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main
from spread.configs import register

register()


@console_main("spread-train", config="train")
def main(cfg: DictConfig) -> None:
    from spread.commands.train import train

    train(cfg)


if __name__ == "__main__":
    main()
