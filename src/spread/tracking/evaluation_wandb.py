"""An evaluation on wandb (conventions: :mod:`spread.tracking.loggers`): its metrics as summary + one log
step (as ``metrics.json`` has them), a per-scene table whose first rows carry the top-down renders (each value in
its display unit, headed so: ``asd_mm``), and the renders themselves.
:func:`log_metrics` also serves a sampling run evaluated in the same command (``spread-sample
evaluate=true``). Offline by default; ``mode="disabled"`` writes nothing and opens no connection.
"""

from __future__ import annotations

from pathlib import Path

def table_columns(metrics: dict) -> list[str]:
    """Per-scene table columns (besides ``scene_id`` and ``render``), as in ``per_scene.jsonl``: the object count,
    every value (:attr:`~spread.metrics.registry.MetricSpec.values`) of the metrics the evaluation selected (its
    protocol's ``metrics``), the error."""
    from spread.metrics.registry import METRICS

    names = (metrics.get("protocol") or {}).get("metrics") or [n for n in METRICS.names() if n in metrics]
    values = [v.name for n in names if n in METRICS for v in METRICS.get(n).values]
    return ["num_objects", *values, "error"]


def scalar_metrics(metrics: dict) -> dict:
    """The numeric top-level entries of ``metrics.json`` (what wandb can chart), each value in its display unit
    and keyed so (``asd_mm``: :func:`spread.metrics.registry.in_display_units`), as the run's tables show it."""
    from spread.metrics.registry import in_display_units

    numbers = {k: v for k, v in metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}
    return in_display_units(numbers)


def log_metrics(run, metrics: dict, records: list[dict], renders: list) -> None:
    """An evaluation's metrics (summary + one step), its per-scene table (renders in the first rows) and the
    renders."""
    import wandb

    from spread.tracking.config import room_type_scalars

    scalars = scalar_metrics(metrics)
    boot = metrics.get("bootstrap") or {}  # the intervals' settings, flat (what spread-report reads back)
    scalars |= {f"ci_{k}": boot[k] for k in ("level", "resamples", "seed") if k in boot}
    scalars |= room_type_scalars(metrics)  # the per-room-type breakdown
    run.log(scalars)
    run.summary.update({**scalars, "fid_status": metrics["fid_status"]})
    from spread.runtime.fingerprint import measured_identity

    identity = measured_identity(metrics)  # what the numbers measured with (a report of wandb runs reads it)
    if identity is not None:
        run.config.update({"spread_identity": identity}, allow_val_change=True)
    from spread.metrics.registry import value_spec

    by_name = {Path(p).stem: p for p in renders}
    columns = table_columns(metrics)
    specs = [value_spec(c) for c in columns]  # each value in its display unit, headed so (asd_mm)
    table = wandb.Table(columns=["scene_id", "render", *[c if s is None else s.key for c, s in zip(columns, specs)]])
    for r in records:
        image = wandb.Image(str(by_name[r["scene_id"]])) if r["scene_id"] in by_name else None
        table.add_data(r["scene_id"], image, *[r.get(c) if s is None or r.get(c) is None else s.display(r[c])
                                               for c, s in zip(columns, specs)])
    # the table travels as a wandb artifact (staged in wandb's data dir until `wandb sync`); the renders
    # are also logged on their own, so the run folder under out_dir/wandb holds them
    run.log({"per_scene": table, "renders": [wandb.Image(str(p), caption=Path(p).stem) for p in renders]})


def log_evaluation(result, logger, group: str | None = None, config: dict | None = None,
                   tags: list[str] | None = None, run=None) -> str | None:
    """Log an :class:`~spread.evaluation.run.EvaluationResult` (``job_type=evaluate``) with ``logger`` (a
    :class:`~spread.tracking.loggers.LoggerConfig`); returns the run's folder (None when disabled or when the
    logger is not wandb). ``config``: the command's config (default: the protocol and inputs); ``run``: a run
    opened before the work (else one is opened now); the run is finished."""
    from spread.tracking.loggers import as_logger_config, init_run, run_folder

    logger = as_logger_config(logger)
    if not logger.wandb:
        return None
    config = config if config is not None else {
        "protocol": result.metrics["protocol"], "scenes": result.metrics["scenes"],
        "reference": result.metrics["reference"], "versions": result.metrics["versions"]}
    run = run if run is not None else init_run(logger, "evaluate", result.out_dir, config, group=group, tags=tags,
                                               name=Path(result.out_dir).name)
    try:
        log_metrics(run, result.metrics, result.records, result.renders)
        return run_folder(run)
    finally:
        run.finish()
