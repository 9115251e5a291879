"""Runs on wandb, with one set of conventions so they line up on the dashboard:

* ``project`` (``spread``), ``group`` = the experiment (``experiment_name``: the training experiment, the
  ablation, the sweep), ``job_type`` = ``train`` | ``sample`` | ``evaluate``, ``tags`` = variant, sampler,
  guidance mode and weights (``collision=0.0075`` …), ``config`` = the command's whole composed config.
* An evaluation: its metrics as summary + one log step, a per-scene table whose first rows carry the
  top-down renders, and the renders themselves. A sampling run: its counts and timings, and, with
  ``evaluate=true``, the same metrics and table.

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


def init_run(job_type: str, out_dir: str | Path, config: dict, mode: str = "offline", project: str = "spread",
             group: str | None = None, name: str | None = None, tags: list[str] | None = None):
    """``wandb.init`` with the conventions of the module docstring; files under ``out_dir/wandb``."""
    import wandb

    return wandb.init(project=project, group=group, job_type=job_type, name=name, tags=tags, dir=str(out_dir),
                      mode=mode, config=config, reinit="finish_previous",
                      settings=wandb.Settings(console="off", save_code=False, silent=True))


def log_metrics(run, metrics: dict, records: list[dict], renders: list) -> None:
    """An evaluation's metrics (summary + one step), its per-scene table (renders in the first rows) and the
    renders."""
    import wandb

    scalars = scalar_metrics(metrics)
    run.log(scalars)
    run.summary.update({**scalars, "fid_status": metrics["fid_status"]})
    by_name = {Path(p).stem: p for p in renders}
    table = wandb.Table(columns=["scene_id", "render", *TABLE_COLUMNS])
    for r in records:
        image = wandb.Image(str(by_name[r["scene_id"]])) if r["scene_id"] in by_name else None
        table.add_data(r["scene_id"], image, *[r.get(c) for c in TABLE_COLUMNS])
    # the table travels as a wandb artifact (staged in wandb's data dir until `wandb sync`); the renders
    # are also logged on their own, so the run folder under out_dir/wandb holds them
    run.log({"per_scene": table, "renders": [wandb.Image(str(p), caption=Path(p).stem) for p in renders]})


def log_evaluation(result, mode: str = "offline", project: str = "spread", name: str | None = None,
                   tags: list[str] | None = None, group: str | None = None, config: dict | None = None) -> str | None:
    """Log an :class:`~spread.distributed.evaluation.EvaluationResult` (``job_type=evaluate``); returns the
    run's folder (None when disabled). ``config``: the command's config (default: the protocol and inputs)."""
    config = config if config is not None else {
        "protocol": result.metrics["protocol"], "scenes": result.metrics["scenes"],
        "reference": result.metrics["reference"], "versions": result.metrics["versions"]}
    run = init_run("evaluate", result.out_dir, config, mode, project, group, name, tags)
    try:
        log_metrics(run, result.metrics, result.records, result.renders)
        return None if mode == "disabled" else str(getattr(run, "dir", "") or "")
    finally:
        run.finish()


def log_sampling(manifest: dict, out_dir: str | Path, config: dict, mode: str = "offline", project: str = "spread",
                 group: str | None = None, name: str | None = None, tags: list[str] | None = None,
                 evaluation=None) -> str | None:
    """Log a sampling run (``sampling.json``: counts, timings, guidance) with ``job_type=sample``; with an
    :class:`~spread.distributed.evaluation.EvaluationResult` also its metrics and per-scene table, the
    sampling's ground truth | generated renders in the table's first rows."""
    import wandb

    run = init_run("sample", out_dir, config, mode, project, group, name, tags)
    try:
        numbers = {f"sampling/{k}": manifest[k] for k in ("samples", "written_this_run", "seconds",
                                                          "seconds_per_batch", "repaired_rotations")
                   if isinstance(manifest.get(k), (int, float))}
        numbers |= {f"guidance/{k}": v for k, v in (manifest.get("guidance_totals") or {}).items()}
        run.log(numbers)
        run.summary.update(numbers)
        if evaluation is not None:
            log_metrics(run, evaluation.metrics, evaluation.records, list(manifest.get("renders") or []))
        elif manifest.get("renders"):
            run.log({"renders": [wandb.Image(str(p), caption=Path(p).stem) for p in manifest["renders"]]})
        return None if mode == "disabled" else str(getattr(run, "dir", "") or "")
    finally:
        run.finish()
