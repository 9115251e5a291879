"""``spread-train-ray experiment=NAME data.root=DIR ray_train.num_workers=N``: ``spread-train`` on Ray Train
(:mod:`spread.training.ray_train`; ``trainer=ray`` unless the command line names a trainer)."""

from __future__ import annotations

import sys

from omegaconf import DictConfig

from spread.cli.errors import console_main
from spread.configs import register
from spread.training.ray_train import with_default_trainer

register()


@console_main("spread-train-ray", config="train")  # its command line checked after main() rewrote it
def _main(cfg: DictConfig) -> None:
    from spread.data.splits import check_fit_config
    from spread.runtime.ray import address_problem
    from spread.training.ray_train import ray_train_settings

    problem = address_problem(ray_train_settings(cfg).address, "ray_train.address")  # each key, the cluster's
    if problem:  # address: before the folder's lock, record and Ray (a join retried for minutes)
        raise ValueError(problem)
    check_fit_config(cfg)  # data without scenes: refused before torch, Lightning and Ray load
    from spread.commands.common import record_config
    from spread.io import run_lock
    from spread.training.fit import check_start, run_folder
    from spread.training.ray_train import run_ray_train

    with run_lock(run_folder(cfg), "spread-train"):  # the folder's one training run, as spread-train holds it
        check_start(cfg, run_folder(cfg))  # refused here in one line, before Ray starts and the config is recorded
        record_config(cfg, run_folder(cfg))()
        result = run_ray_train(cfg, run_folder(cfg))
    summary = result.return_value or {}
    print(f"run folder {run_folder(cfg)}: step {summary.get('global_step')}, epoch {summary.get('epoch')}, "
          f"{summary.get('world_size')} Ray Train workers, checkpoint {summary.get('last_checkpoint')}; "
          f"Ray checkpoint {None if result.checkpoint is None else result.checkpoint.path}")


def main() -> None:
    sys.argv = with_default_trainer(sys.argv)  # checked as it composes: trainer=ray unless the line names one
    _main()


if __name__ == "__main__":
    main()
