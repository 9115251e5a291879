"""``spread-train experiment=NAME data.root=DIR``: train one variant with Lightning (DESIGN §5).

The run folder is Hydra's output dir (``out_dir``, by default ``runs/train/<experiment>/<time>``):
``.hydra/`` (the composed config), ``checkpoints/`` (``last.ckpt`` and the newest periodic one),
``csv/version_<n>/metrics.csv`` (one version per launch), ``wandb/`` (offline unless ``WANDB_MODE`` says
otherwise) and ``metrics.json`` (the final step and logged values). The data module, model and trainer
are ``_target_`` nodes of the config (``conf/data``, ``conf/model``, ``conf/trainer``); this file adds
the run folder, the loggers, the callbacks, the final checkpoint and the resume logic.

``ckpt_path``: ``null`` starts a new run; a path resumes from that checkpoint (weights, EMA, optimizer,
global step, loop state); ``last`` resumes ``<out_dir>/checkpoints/last.ckpt`` when it exists, else the
newest ``<paths.runs_dir>/train/<experiment_name>/*/checkpoints/last.ckpt``, else starts a new run (so a
preempted job can always be relaunched with ``ckpt_path=last out_dir=<its folder>``).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Callable

import hydra
from lightning.pytorch.callbacks import Callback
from omegaconf import DictConfig, OmegaConf

from spread.cli import conf_dir

log = logging.getLogger("spread.train")


def run_folder(cfg: DictConfig) -> Path:
    """Hydra's output dir inside a Hydra app (also in DDP child processes); ``cfg.out_dir`` otherwise."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path(str(cfg.out_dir))


def set_threads(threads: int | None) -> None:
    """torch intra-op threads (None: torch's default). One thread is much faster on a shared 2-core CPU."""
    if threads:
        import torch

        torch.set_num_threads(int(threads))


def route_lightning_logs() -> None:
    """Lightning prints its messages with its own handler; inside a Hydra app the root logger already
    prints them (and writes the run's log file), so drop Lightning's handler to print each line once."""
    if not logging.getLogger().handlers:
        return
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logger = logging.getLogger(name)
        for handler in [h for h in logger.handlers if type(h) is logging.StreamHandler]:
            logger.removeHandler(handler)
        logger.propagate = True


def resolve_ckpt_path(cfg: DictConfig, run_dir: Path) -> Path | None:
    """The checkpoint to resume from, following the rules of the module docstring."""
    value = cfg.get("ckpt_path")
    if value in (None, "", "null"):
        return None
    if str(value) != "last":
        path = Path(str(value))
        if not path.is_file():
            raise SystemExit(f"spread-train: ckpt_path={value}: no such checkpoint file")
        return path
    own = run_dir / "checkpoints" / "last.ckpt"
    if own.is_file():
        return own
    runs = Path(str(cfg.paths.runs_dir)) / "train" / str(cfg.experiment_name)
    found = sorted(runs.glob("*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime)
    if found:
        return found[-1]
    log.warning("ckpt_path=last: no last.ckpt in %s or under %s; starting a new run", own.parent, runs)
    return None


def previous_wandb_id(run_dir: Path) -> str | None:
    """The id of the newest wandb run in ``<run folder>/wandb`` (``latest-run`` → ``…-run-<time>-<id>``)."""
    latest = run_dir / "wandb" / "latest-run"
    return latest.resolve().name.rsplit("-", 1)[-1] if latest.exists() else None


def build_loggers(cfg: DictConfig, run_dir: Path, resuming_here: bool = False) -> list:
    """``logger=wandb``: WandbLogger (project, mode, group = experiment, job_type train, tags) + CSVLogger;
    ``logger=csv``: CSVLogger only; ``logger=none``: no logger. ``resuming_here``: the run continues from
    this folder's own checkpoint, so it continues this folder's wandb run too (same id)."""
    from lightning.pytorch.loggers import CSVLogger, WandbLogger

    name = str(cfg.logger.name)
    if name == "none":
        return []
    if name not in ("wandb", "csv"):
        raise SystemExit(f"spread-train: unknown logger '{name}' (wandb, csv or none)")
    loggers = [CSVLogger(save_dir=str(run_dir), name="csv")]  # csv/version_<n>: a resumed run never overwrites
    if name == "wandb":
        config = OmegaConf.to_container(cfg, resolve=True)
        loggers.insert(0, WandbLogger(
            project=str(cfg.logger.project), name=cfg.logger.get("run_name") or f"{cfg.experiment_name}/{run_dir.name}",
            save_dir=str(run_dir), mode=str(cfg.logger.mode), group=str(cfg.experiment_name), job_type="train",
            tags=[str(t) for t in cfg.tags], config=config, log_model=False,
            id=previous_wandb_id(run_dir) if resuming_here else None))
    return loggers


def build_callbacks(cfg: DictConfig, run_dir: Path) -> list:
    """ModelCheckpoint into ``<run folder>/checkpoints`` plus the ``callbacks`` of the config."""
    checkpoint = hydra.utils.instantiate(cfg.checkpoint, dirpath=str(run_dir / "checkpoints"))
    return [checkpoint] + [hydra.utils.instantiate(c) for c in (cfg.get("callbacks") or {}).values()]


class CheckpointStep(Callback):
    """Remembers the global step of the newest checkpoint this run saved or resumed from."""

    def __init__(self):
        self.step: int | None = None

    def on_save_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        self.step = int(trainer.global_step)

    def on_load_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        self.step = int(checkpoint.get("global_step", -1))


def save_final_checkpoint(trainer, run_dir: Path, newest: CheckpointStep) -> None:
    """``checkpoints/last.ckpt`` = the state at the end of ``fit``, when no checkpoint holds it yet.
    ModelCheckpoint saves "last" only at its own moments (every n steps, epoch ends), so a run stopped by
    ``max_time`` mid-epoch would otherwise leave a last.ckpt behind the trained weights. A resumed run that
    takes no step leaves the file untouched (same bytes, so samplers keyed on its hash stay valid)."""
    if trainer.fast_dev_run or trainer.checkpoint_callback is None or trainer.global_step == 0:
        return
    if newest.step != trainer.global_step:
        trainer.save_checkpoint(run_dir / "checkpoints" / "last.ckpt")


def write_summary(trainer, run_dir: Path, resumed_from: Path | None) -> dict:
    """``<run folder>/metrics.json``: final step, epoch, last checkpoint, logged values (rank zero only)."""
    from spread.io import write_json_atomic

    last = run_dir / "checkpoints" / "last.ckpt"
    summary = {
        "global_step": int(trainer.global_step), "epoch": int(trainer.current_epoch),
        "last_checkpoint": str(last) if last.exists() else None,
        "resumed_from": None if resumed_from is None else str(resumed_from),
        "metrics": {k: float(v) for k, v in trainer.callback_metrics.items() if v.numel() == 1},
    }
    if trainer.is_global_zero:
        write_json_atomic(run_dir / "metrics.json", summary)
    return summary


def atomic_checkpoint_io():
    """A Lightning ``TorchCheckpointIO`` that writes each checkpoint to a temp file beside its target and
    renames it (:func:`spread.io.atomic_path`): a job killed mid-save never leaves a torn ``last.ckpt``, also
    when TMPDIR is on another filesystem than the run folder (where a rename falls back to a copy)."""
    import torch
    from lightning.pytorch.plugins.io import TorchCheckpointIO

    from spread.io import atomic_path

    class AtomicCheckpointIO(TorchCheckpointIO):
        def save_checkpoint(self, checkpoint, path, storage_options=None) -> None:
            if storage_options is not None:
                raise TypeError(f"AtomicCheckpointIO: storage_options are not supported (got {storage_options!r})")
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(path) as tmp:
                torch.save(checkpoint, tmp)

    return AtomicCheckpointIO()


def train(cfg: DictConfig, run_dir: Path | None = None, *, trainer_overrides: dict | None = None,
          extra_callbacks: list | None = None, prepare: Callable | None = None,
          resume_from: Path | None = None) -> dict:
    """Fit the configured model on the configured data into ``run_dir``; returns the summary.

    The keyword arguments let another launcher run this same code (Ray Train,
    :mod:`spread.distributed.ray_train`): ``trainer_overrides`` replace Trainer arguments of ``cfg.trainer``
    (strategy, plugins, devices, ...), ``extra_callbacks`` join the config's, ``prepare(trainer) -> trainer``
    runs before ``fit``, and ``resume_from`` (a checkpoint file) wins over ``ckpt_path``."""
    import lightning as L

    run_dir = Path(run_dir) if run_dir is not None else run_folder(cfg)
    run_dir.mkdir(parents=True, exist_ok=True)
    route_lightning_logs()
    set_threads(cfg.get("threads"))
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    ckpt_path = Path(resume_from) if resume_from is not None else resolve_ckpt_path(cfg, run_dir)
    resuming_here = ckpt_path is not None and ckpt_path.resolve().parent == (run_dir / "checkpoints").resolve()
    datamodule = hydra.utils.instantiate(cfg.data)
    model = hydra.utils.instantiate(cfg.model)
    newest = CheckpointStep()
    overrides = dict(trainer_overrides or {})
    plugins = [atomic_checkpoint_io(), *(overrides.pop("plugins", None) or [])]
    trainer = hydra.utils.instantiate(cfg.trainer, default_root_dir=str(run_dir),
                                      logger=build_loggers(cfg, run_dir, resuming_here) or False,
                                      callbacks=build_callbacks(cfg, run_dir) + [newest, *(extra_callbacks or [])],
                                      plugins=plugins, **overrides)
    if prepare is not None:
        trainer = prepare(trainer)
    if ckpt_path is not None:
        log.info("resuming from %s", ckpt_path)
    trainer.fit(model, datamodule=datamodule, ckpt_path=None if ckpt_path is None else str(ckpt_path))
    save_final_checkpoint(trainer, run_dir, newest)
    summary = write_summary(trainer, run_dir, ckpt_path)
    if trainer.is_global_zero:
        print(f"run folder {run_dir}: step {summary['global_step']}, epoch {summary['epoch']}, "
              f"checkpoint {summary['last_checkpoint']}")
    return summary


@hydra.main(config_path=conf_dir(), config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> None:
    train(cfg)


if __name__ == "__main__":
    main()
