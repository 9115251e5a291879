"""``spread-evaluate``'s body: one evaluation run, logged (wandb, MLflow), and its console summary."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from spread.commands.common import failed_on_error, plain, record_config
from spread.configs import to_object


def evaluate(cfg: DictConfig, overrides: list[str] | None = None):
    """``spread-evaluate``: evaluate ``cfg.scenes``; logs to wandb with ``logger=wandb``; returns the
    :class:`~spread.evaluation.EvaluationResult`. The config is recorded in ``out_dir/.hydra`` once the
    protocol check passed."""
    from spread.io import run_lock

    command = to_object(cfg)
    # the lock before the trackers: a refused second run writes no tracker record
    with run_lock(command.out_dir, "spread-evaluate", nest=True):
        return _evaluate(cfg, command, overrides)


def _evaluate(cfg: DictConfig, command, overrides: list[str] | None):
    from spread.evaluation import run_evaluation
    from spread.tracking.evaluation_wandb import log_evaluation
    from spread.tracking import mlflow_store as mlflow_log

    tags = {"spread.seed": command.seed, "spread.scenes": str(command.scenes),
            "spread.dataset_fingerprint": mlflow_log.dataset_fingerprint(command.reference)}
    lineage = scenes_lineage(command.scenes)
    again = evaluation_continuation(command, plain(cfg))
    wandb_run = None
    if command.logger.wandb:
        from spread.tracking.loggers import init_run

        Path(command.out_dir).mkdir(parents=True, exist_ok=True)
        wandb_run = init_run(command.logger, "evaluate", command.out_dir, plain(cfg) | {"lineage": lineage},
                             group=command.experiment_name, name=Path(command.out_dir).name, run_id=again.wandb_id())
    with failed_on_error(wandb_run):
        with mlflow_log.tracked(command.logger, "evaluate", command.out_dir, plain(cfg), command.experiment_name,
                                tags=tags | lineage, continuation=again) as run:
            result = run_evaluation(command, before_work=again.recorded(
                record_config(cfg, command.out_dir, overrides), run, wandb_run))
            if run is not None:
                mlflow_log.log_evaluation(run, result.metrics, result.out_dir, result.renders)
    log_evaluation(result, command.logger, group=command.experiment_name, config=plain(cfg), run=wandb_run)
    return result


def evaluation_continuation(command, config: dict):
    """Whether this launch continues the folder's tracker runs (:mod:`spread.tracking.continuation`): the
    identity of its results is what ``metrics.json`` records them measured with
    (:func:`spread.evaluation.run.evaluated_with`) and the scenes' folder and content."""
    from spread.evaluation.run import evaluated_with
    from spread.runtime.fingerprint import tree_digest
    from spread.tracking.continuation import Continuation

    def identity() -> dict:
        scenes = Path(str(command.scenes))
        return {**evaluated_with(command, str(Path(str(command.reference)) / "assets")),
                "scenes": str(scenes.resolve()), "scenes_sha256": tree_digest(scenes)}

    return Continuation(command.out_dir, "evaluate", identity, command.resume, config)


def evaluated_specs(metrics: dict) -> list:
    """The registered metrics a ``metrics.json`` holds (its protocol's selection), in table order."""
    from spread.metrics.registry import METRICS, ordered

    names = (metrics.get("protocol") or {}).get("metrics") or [n for n in METRICS.names() if n in metrics]
    return ordered(METRICS.get(n) for n in names if n in METRICS)


def scenes_lineage(scenes) -> dict:
    """Lineage tags of an evaluation of ``scenes``: a sampling run's ``scenes/`` folder names the sampling
    run (its :data:`~spread.tracking.mlflow_store.RUN_FILE`) and, through its recorded checkpoint, the training run."""
    from spread.io import read_json

    from spread.tracking.mlflow_store import job_run_id, training_lineage

    folder = Path(scenes).parent
    tags = {}
    sampling_run = job_run_id(folder, "sample")  # not the folder's own evaluation's run, when it has one
    if sampling_run:
        tags["spread.sampling_run_id"] = sampling_run
    manifest = folder / "sampling.json"
    if manifest.exists():
        tags |= training_lineage(read_json(manifest).get("ckpt"))
    return tags


def print_evaluation_summary(metrics: dict, out_dir) -> None:
    """The evaluation's console table: each value of the evaluated metrics in its display unit (the table writer's
    columns, :func:`spread.reporting.tables.metric_column`), its 95 % bootstrap interval over scenes where it has
    one."""
    from rich.console import Console
    from rich.table import Table

    from spread.evaluation.bootstrap import interval_note
    from spread.reporting.tables import metric_column, set_columns

    def fmt(v, digits=4):
        return "null" if v is None else (f"{v:.{digits}f}" if isinstance(v, float) else str(v))

    def interval(column, row):
        lo, hi = row.get(f"{column.key}_lo"), row.get(f"{column.key}_hi")
        return "" if lo is None or hi is None else f"[{column.format(lo)}, {column.format(hi)}]"

    level = (metrics.get("bootstrap") or {}).get("level")
    table = Table(title=f"evaluation {out_dir}")
    table.add_column("metric")
    table.add_column("value", justify="right")
    table.add_column(f"{level * 100:g} % interval" if level else "interval", justify="right")
    specs = evaluated_specs(metrics)
    values = [v for spec in specs for v in spec.values if v.name in metrics]
    for value in values:
        column = metric_column(value)
        arrow = "↑" if value.higher_is_better else "↓"
        table.add_row(f"{value.label} ({value.description or value.name}, {arrow})",
                      column.format(metrics.get(value.name)), interval(column, metrics))
    fid, kid = set_columns()
    table.add_row(f"{fid.label} ({metrics.get('fid_feature_model')}, ↓)", fid.format(metrics.get("fid")))
    table.add_row(f"{kid.label} (↓)", kid.format(metrics.get("kid")))
    table.add_row("scenes / evaluated / failed",
                  f"{metrics['n_scenes']} / {metrics['n_evaluated']} / {metrics['n_failed']}")
    table.add_row("objects", str(metrics["n_objects"]))
    table.add_row("seconds", fmt(metrics["run"]["seconds"], 1))
    console = Console()
    console.print(table)
    if metrics.get("per_room_type"):
        by_type = Table(title="per room type")
        columns = [metric_column(v) for v in values]
        for col in ("room type", "scenes", *[c.label for c in columns]):
            by_type.add_column(col, justify="left" if col == "room type" else "right")
        for name, m in metrics["per_room_type"].items():
            by_type.add_row(name, str(m["n_evaluated"]), *[c.format(m.get(c.key)) for c in columns])
        console.print(by_type)
    note = interval_note(metrics.get("bootstrap"))
    if note:
        console.print(note.replace("± is half the width of the", "interval: the"), soft_wrap=True)
    console.print(f"fid_status: {metrics['fid_status']}", markup=False, soft_wrap=True)  # a path: kept whole
    for f in metrics["failed"][:10]:
        console.print(f"failed {f['scene_id']}: {f['error']}", markup=False, soft_wrap=True)
    failures = {k: v for k, v in (metrics.get("metric_failures") or {}).items() if v}
    if failures:
        console.print("metric failures (those scenes are left out of that metric only): "
                      + ", ".join(f"{k} on {v} scene(s)" for k, v in failures.items()), markup=False)
        for f in (metrics.get("failed_metrics") or [])[:10]:
            console.print(f"  {f['metric']} failed on {f['scene_id']}: {f['error']}", markup=False)
    for name, why in (metrics.get("invalid_values") or {}).items():
        console.print(f"{name}: no value ({why})", markup=False)
