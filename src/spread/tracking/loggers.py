"""Experiment tracking: the ``logger`` config, the one factory of loggers, and the wandb conventions.

Every command logs through here, with one set of conventions so runs line up on the dashboard:
``project`` (``spread``), ``group`` = the experiment (the training experiment, the ablation, the sweep),
``job_type`` = ``train`` | ``sample`` | ``evaluate`` | ``ablation``, ``tags`` = variant, sampler, guidance
mode and weights, ``config`` = the command's whole composed config.

``logger.name``: ``wandb`` (offline by default: files under ``<run folder>/wandb``, ``wandb sync``
uploads them later; ``WANDB_MODE`` overrides ``mode``), ``mlflow`` (a local MLflow store, by default
``sqlite:///<paths.runs_dir>/mlflow.db``; ``logger.tracking_uri`` points elsewhere; ``spread-dashboard``
serves its UI; :mod:`spread.tracking.mlflow_store`), ``csv`` (Lightning's CSV files; the other commands
log nothing) or ``none``. Several at once: ``logger.name=wandb+mlflow``. Nothing here opens a network
connection in the offline and disabled modes (nor with a local MLflow store).
"""

from __future__ import annotations

from pathlib import Path

from spread.tracking.config import NAMES, LoggerConfig, as_logger_config, previous_wandb_id  # noqa: F401


def init_run(logger: LoggerConfig, job_type: str, out_dir: str | Path, config: dict, group: str | None = None,
             name: str | None = None, tags: list[str] | None = None, run_id: str | None = None):
    """``wandb.init`` with the conventions of the module docstring; files under ``out_dir/wandb``."""
    import wandb

    return wandb.init(project=logger.project, group=group or None, job_type=job_type, name=logger.run_name or name,
                      tags=[*(tags or []), *logger.tags], dir=str(out_dir), mode=logger.mode, config=config,
                      id=run_id, resume="allow" if run_id else None, reinit="finish_previous",
                      settings=wandb.Settings(console="off", save_code=False, silent=True))


def run_folder(run) -> str | None:
    """The wandb run's folder (None when wandb is disabled)."""
    return None if run.settings.mode == "disabled" else str(getattr(run, "dir", "") or "")


def lightning_loggers(logger: LoggerConfig, run_dir: Path, group: str, tags: list[str], config: dict,
                      resuming_here: bool = False) -> list:
    """Lightning loggers for a training run: ``wandb`` → WandbLogger (``job_type=train``) + CSVLogger,
    ``mlflow`` → MLFlowLogger (:func:`spread.tracking.mlflow_store.lightning_logger`) + CSVLogger, ``csv`` →
    CSVLogger, ``none`` → none. The CSV files go to ``csv/version_<n>`` (a resumed run never
    overwrites); ``resuming_here``: the run continues from this folder's own checkpoint, so it continues
    this folder's wandb and MLflow runs too (same ids)."""
    from lightning.pytorch.loggers import CSVLogger, WandbLogger

    if set(logger.names) <= {"none"}:
        return []
    loggers = [CSVLogger(save_dir=str(run_dir), name="csv")]
    if logger.mlflow:
        from spread.tracking.mlflow_store import lightning_logger

        loggers.insert(0, lightning_logger(logger, run_dir, group, tags, config, resuming_here))
    if logger.wandb:
        loggers.insert(0, WandbLogger(
            project=logger.project, name=logger.run_name or f"{group}/{Path(run_dir).name}", save_dir=str(run_dir),
            mode=logger.mode, group=group, job_type="train", tags=[*tags, *logger.tags], config=config,
            log_model=False, id=previous_wandb_id(run_dir) if resuming_here else None))
        getattr(loggers[0], "_wandb_init", {}).pop("anonymous", None)  # wandb warns about the key (runtime.quiet)
    return loggers
