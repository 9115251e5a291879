"""An evaluation's numbers on wandb: the metrics as summary + one log step, a per-scene table whose
first rows carry the top-down renders, and the renders themselves.

Offline by default (``mode="offline"``, files under ``out_dir/wandb``, ``wandb sync`` uploads them later);
``"disabled"`` writes nothing. Nothing here opens a network connection in those modes.
"""

from __future__ import annotations

from pathlib import Path

#: Per-scene table columns (besides ``scene_id`` and ``render``), as in ``per_scene.jsonl``.
TABLE_COLUMNS = ("num_objects", "col_mesh", "grecall", "asd", "stability", "still_fraction", "error")


def scalar_metrics(metrics: dict) -> dict:
    """The numeric top-level entries of ``metrics.json`` (what wandb can chart)."""
    return {k: v for k, v in metrics.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def log_evaluation(result, mode: str = "offline", project: str = "spread", name: str | None = None,
                   tags: list[str] | None = None) -> str | None:
    """Log an :class:`~spread.distributed.evaluation.EvaluationResult`; returns the run's folder (None when
    disabled)."""
    import wandb

    run = wandb.init(project=project, name=name, tags=tags, dir=str(result.out_dir), mode=mode,
                     job_type="evaluate", reinit="finish_previous",
                     config={"protocol": result.metrics["protocol"], "scenes": result.metrics["scenes"],
                             "reference": result.metrics["reference"], "versions": result.metrics["versions"]},
                     settings=wandb.Settings(console="off", save_code=False, silent=True))
    try:
        scalars = scalar_metrics(result.metrics)
        run.log(scalars)
        run.summary.update({**scalars, "fid_status": result.metrics["fid_status"]})
        renders = {Path(p).stem: p for p in result.renders}
        table = wandb.Table(columns=["scene_id", "render", *TABLE_COLUMNS])
        for r in result.records:
            image = wandb.Image(str(renders[r["scene_id"]])) if r["scene_id"] in renders else None
            table.add_data(r["scene_id"], image, *[r.get(c) for c in TABLE_COLUMNS])
        # the table travels as a wandb artifact (staged in wandb's data dir until `wandb sync`); the renders
        # are also logged on their own, so the run folder under out_dir/wandb holds them
        run.log({"per_scene": table,
                 "renders": [wandb.Image(str(p), caption=Path(p).stem) for p in result.renders]})
        return None if mode == "disabled" else str(getattr(run, "dir", "") or "")
    finally:
        run.finish()
