"""``spread-generate out_dir=DIR rooms=N seed=S``: procedural rooms → dataset folder (:mod:`spread.procgen`)."""

from __future__ import annotations

from omegaconf import DictConfig

from spread.cli.errors import console_main


@console_main("spread-generate", config="generate")
def main(cfg: DictConfig) -> None:
    from spread.commands.generate import generate, print_dataset_summary

    print_dataset_summary(generate(cfg), cfg.out_dir)


if __name__ == "__main__":
    main()
