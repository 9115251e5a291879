"""The ablation table on wandb: a ``wandb.Table`` (one row per variant), the bar plot, and per-variant
summary values (``<variant>/<metric>``). Offline by default: files under ``out_dir/wandb``, ``wandb sync``
uploads them later; ``mode="disabled"`` writes nothing and opens no connection."""

from __future__ import annotations

from pathlib import Path

from spread.experiments.tables import METRICS

COLUMNS = ("variant", "method", *[c.key for c in METRICS], "still_fraction", "n_scenes", "fid_status", "status")


def log_ablation(records: list[dict], png: str | Path | None, out_dir: str | Path, logger, name: str | None = None,
                 config: dict | None = None, group: str | None = None) -> str | None:
    """Log the table with ``logger`` (a :class:`~spread.runtime.tracking.LoggerConfig`, ``job_type=ablation``);
    returns the wandb run folder (None when disabled)."""
    import wandb

    from spread.runtime.tracking import as_logger_config, init_run, run_folder

    run = init_run(as_logger_config(logger), "ablation", out_dir, config or {}, group=group, name=name)
    try:
        table = wandb.Table(columns=list(COLUMNS))
        for r in records:
            table.add_data(*[r.get(c) for c in COLUMNS])
        payload = {"ablation": table}
        if png is not None and Path(png).exists():
            payload["ablation_plot"] = wandb.Image(str(png))
        run.log(payload)
        run.summary.update({f"{r['variant']}/{c.key}": r.get(c.key) for r in records for c in METRICS})
        return run_folder(run)
    finally:
        run.finish()
