"""The ablation table on wandb: a ``wandb.Table`` (one row per variant), the bar plot, and per-variant
summary values (``<variant>/<metric>``). Offline by default: files under ``out_dir/wandb``, ``wandb sync``
uploads them later; ``mode="disabled"`` writes nothing and opens no connection."""

from __future__ import annotations

from pathlib import Path

from spread.experiments.tables import METRICS

COLUMNS = ("variant", "method", *[c.key for c in METRICS], "still_fraction", "n_scenes", "fid_status", "status")


def log_ablation(records: list[dict], png: str | Path | None, out_dir: str | Path, mode: str = "offline",
                 project: str = "spread", name: str | None = None, tags: list[str] | None = None,
                 config: dict | None = None, group: str | None = None) -> str | None:
    """Log the table; returns the wandb run folder (None when disabled)."""
    import wandb

    run = wandb.init(project=project, group=group or None, name=name, tags=tags, dir=str(out_dir), mode=mode,
                     job_type="ablation",
                     reinit="finish_previous", config=config or {},
                     settings=wandb.Settings(console="off", save_code=False, silent=True))
    try:
        table = wandb.Table(columns=list(COLUMNS))
        for r in records:
            table.add_data(*[r.get(c) for c in COLUMNS])
        payload = {"ablation": table}
        if png is not None and Path(png).exists():
            payload["ablation_plot"] = wandb.Image(str(png))
        run.log(payload)
        run.summary.update({f"{r['variant']}/{c.key}": r.get(c.key) for r in records for c in METRICS})
        return None if mode == "disabled" else str(getattr(run, "dir", "") or "")
    finally:
        run.finish()
