"""``spread-sweep``'s body: the sweep of a command line (:func:`spread.experiments.sweep.parse_arguments`), its
trials running this package's commands in Ray Tune's trial processes
(:class:`~spread.commands.in_process.InProcessCommands`). Before any trial, the trials' stores are pinned to
absolute paths and, with ``logger=mlflow``, the sweep's parent run opens: every trial's run is nested under it
and every point a relaunch re-used gets a child run of its own (:mod:`spread.tracking.parent`)."""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path


def sweep(args: list[str]):
    """Parse the command line's arguments into a plan and run it; returns the
    :class:`~spread.experiments.sweep.SweepResult` (``ValueError``: a bad setting, before any trial)."""
    from spread.commands.in_process import InProcessCommands
    from omegaconf import OmegaConf

    from spread.configs import compose, required_message
    from spread.experiments.sweep import checked_sweep, parse_arguments, run_sweep
    from spread.tracking.parent import absolute_tracking_overrides, parent_run

    plan = parse_arguments(args)
    s = plan.settings
    cfg = compose(s.command, [*plan.fixed, "out_dir=unset"])
    missing = sorted(k for k in OmegaConf.missing_keys(cfg) if k not in {d.key for d in plan.dimensions})
    if missing:  # every one named at once, before any trial (a trial would stop at the first it reads)
        raise ValueError(required_message(missing, "`spread-sweep --help` lists the sweep's own settings"))
    plan.fixed += absolute_tracking_overrides(cfg)  # a trial runs in Ray Tune's folder, not here
    config = {"sweep": asdict(s), "fixed": list(plan.fixed), "dimensions": [asdict(d) for d in plan.dimensions]}
    shared = checked_sweep(plan)  # a refused sweep opens no parent run
    with parent_run(cfg.logger, "sweep", s.name, s.out_dir, s.name, config) as parent:
        result = run_sweep(plan, InProcessCommands(), shared)
        parent.log_reused(result.rows, Path(s.out_dir).resolve() / "points")
        parent.log_files([result.csv, result.md])
    return result
