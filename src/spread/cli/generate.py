"""``spread-generate out_dir=DIR rooms=N seed=S``: procedural rooms → dataset folder (:mod:`spread.procgen`).

SIGTERM ends the command and its worker processes with status 143 and one line (Ctrl-C: 130); the rooms written
stay, and a relaunch makes the others (:func:`spread.runtime.ray.sigterm_exits`)."""

from __future__ import annotations

import sys

from omegaconf import DictConfig

from spread.cli.errors import console_main


@console_main("spread-generate", config="generate")
def main(cfg: DictConfig) -> None:
    from spread.commands.generate import generate, print_dataset_summary
    from spread.runtime.ray import TERMINATED

    try:
        manifest = generate(cfg)
    except SystemExit as exc:
        if exc.code == TERMINATED:
            print("spread-generate: terminated (SIGTERM); a relaunch continues the dataset (the rooms written stay)",
                  file=sys.stderr, flush=True)
        raise
    print_dataset_summary(manifest, cfg.out_dir)


if __name__ == "__main__":
    main()
