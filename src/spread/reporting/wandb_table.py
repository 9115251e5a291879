"""The ablation table on wandb: a ``wandb.Table`` (one row per variant; each metric in its display unit, headed as
in the CSV (``asd_mm``), its bootstrap bounds and the bootstrap's seed beside it), the bar plot, the figures (``ablation_<row>.png`` in ``out_dir``: one test graph per
row in 3D with its relation matrix), and per-variant summary values (``<variant>/<metric>``, ``_lo``, ``_hi``; in
display units, keyed so: ``<variant>/asd_mm``).
Offline by default: files under ``out_dir/wandb``, ``wandb sync`` uploads them later; ``mode="disabled"`` writes
nothing and opens no connection."""

from __future__ import annotations

from pathlib import Path

from spread.reporting.tables import columns_of, display_rows, with_bounds


def table_keys(records: list[dict]) -> list[str]:
    """The wandb table's columns: the row labels, every value the rows have (the registry's), counts, status."""
    return ["variant", "method", *[c.key for c in columns_of(records, hidden=True)], "n_scenes", "fid_status",
            "status"]


def log_ablation(records: list[dict], png: str | Path | None, out_dir: str | Path, logger, name: str | None = None,
                 config: dict | None = None, group: str | None = None) -> str | None:
    """Log the table with ``logger`` (a :class:`~spread.tracking.loggers.LoggerConfig`, ``job_type=ablation``);
    returns the wandb run folder (None when disabled)."""
    import wandb

    from spread.tracking.loggers import as_logger_config, init_run, run_folder

    run = init_run(as_logger_config(logger), "ablation", out_dir, config or {}, group=group, name=name)
    try:
        header, rows = display_rows(records, with_bounds(table_keys(records), records))  # display units (ASD mm)
        table = wandb.Table(columns=header)
        for row in rows:
            table.add_data(*row)
        payload = {"ablation": table}
        if png is not None and Path(png).exists():
            payload["ablation_plot"] = wandb.Image(str(png))
        for k in ("truth", *[r["variant"] for r in records]):
            figure = Path(out_dir) / f"ablation_{k}.png"
            if figure.exists():
                payload[f"ablation_figure/{k}"] = wandb.Image(str(figure))
        run.log(payload)
        from spread.metrics.registry import in_display_units

        run.summary.update({f"{r['variant']}/{key}": value for r in records for key, value in in_display_units(
            {key: r.get(key) for c in columns_of(records) for key in (c.key, f"{c.key}_lo", f"{c.key}_hi")
             if key in r}).items()})
        return run_folder(run)
    finally:
        run.finish()
