"""A sampling run on wandb (``job_type=sample``; conventions: :mod:`spread.tracking.loggers`): its counts,
timings and guidance totals, the ground truth | generated renders, and tags for the variant, the sampler's label
and the guidance (``guidance=<mode>`` and ``<term>=<weight>`` for every registered term that acts). Offline by default; ``mode="disabled"`` writes nothing and opens no connection."""

from __future__ import annotations

from pathlib import Path


def sampling_tags(ckpt: str, sampler, guidance, extra: list[str] | None = None) -> list[str]:
    """Variant (from the checkpoint's hyperparameters, read without loading its weights), the
    :class:`~spread.model.Sampler`'s label and the :class:`~spread.guidance.GuidanceConfig`'s tags, plus ``extra``."""
    from spread import readonce
    from spread.runtime.fingerprint import guidance_run, sampler_label
    from spread.safe_load import checkpoint_identity

    held = checkpoint_identity(readonce.checkpoint(ckpt))
    guidance = guidance_run(ckpt, guidance)  # what runs: the release's paper is its refinement
    tags = [str(held["variant"] or held["method"]), sampler_label(ckpt, sampler)]  # SPREAD variant or baseline
    if guidance.active:
        tags += ["guidance", f"guidance={guidance.mode}"] + [f"{name}={weight:g}" for name, weight
                                                             in guidance.weights(nonzero=True).items()]
    return tags + [str(t) for t in (extra or [])]


def image_groups(manifest: dict) -> dict[str, list[str]]:
    """A sampling run's pictures as wandb keys, one size per key (wandb shows a list of mixed sizes wrongly, and
    says so): ``renders`` (ground truth | generated), and each figure kind apart, ``figures/<kind>`` by the name's
    last part (``<sample>_3d.png``, ``<sample>_physics.png``)."""
    groups: dict[str, list[str]] = {}
    if manifest.get("renders"):
        groups["renders"] = [str(p) for p in manifest["renders"]]
    for path in manifest.get("figures") or []:
        groups.setdefault(f"figures/{Path(path).stem.rsplit('_', 1)[-1]}", []).append(str(path))
    return groups


def open_sampling_run(command, config: dict, group: str, run_id: str | None = None):
    """The wandb run of a ``spread-sample`` command, opened before the work: named after its run folder, tags
    of :func:`sampling_tags` (the guidance from the command), and ``config["lineage"]``: the training run of
    its checkpoint (:func:`spread.tracking.mlflow_store.training_lineage`: its folder, wandb and MLflow ids).
    ``run_id``: a relaunch continues that run (:mod:`spread.tracking.continuation`)."""
    from spread.tracking.mlflow_store import training_lineage
    from spread.tracking.loggers import init_run

    Path(command.out_dir).mkdir(parents=True, exist_ok=True)
    tags = sampling_tags(command.ckpt, command.sampler, command.guidance, command.tags)
    return init_run(command.logger, "sample", command.out_dir, config | {"lineage": training_lineage(command.ckpt)},
                    group=group, name=Path(command.out_dir).name, tags=tags, run_id=run_id)


def log_sampling(manifest: dict, out_dir: str | Path, config: dict, logger, group: str | None = None,
                 tags: list[str] | None = None, evaluation=None, run=None) -> str | None:
    """Log a sampling run (``sampling.json``: counts, timings, guidance) with ``logger`` (a
    :class:`~spread.tracking.loggers.LoggerConfig`); ``evaluation``: the scenes' evaluation in the same command
    (``spread-sample evaluate=true``; ``metrics`` and ``records``), logged into the same run with the renders beside
    its per-scene table; the renders and each kind of 3D figure under keys of their own, one picture size per key
    (:func:`image_groups`). ``run``: a run opened before the work (:func:`open_sampling_run`), else one is opened
    now. The run is finished. Returns the run folder (None when not logged)."""
    import wandb

    from spread.tracking.loggers import as_logger_config, init_run, run_folder

    logger = as_logger_config(logger)
    if not logger.wandb:
        return None
    run = run if run is not None else init_run(logger, "sample", out_dir, config, group=group, tags=tags)
    try:
        numbers = {f"sampling/{k}": manifest[k] for k in ("samples", "written_this_run", "seconds",
                                                          "seconds_per_batch", "startup_seconds", "repaired_rotations")
                   if isinstance(manifest.get(k), (int, float))}
        numbers |= {f"guidance/{k}": v for k, v in (manifest.get("guidance_totals") or {}).items()}
        run.log(numbers)
        run.summary.update(numbers)
        groups = image_groups(manifest)
        if evaluation is not None:  # its metrics, and the renders beside its per-scene table
            from spread.tracking.evaluation_wandb import log_metrics

            log_metrics(run, evaluation.metrics, evaluation.records, groups.pop("renders", []))
        images = {key: [wandb.Image(str(p), caption=Path(p).stem) for p in paths] for key, paths in groups.items()}
        if images:
            run.log(images)
        return run_folder(run)
    finally:
        run.finish()
