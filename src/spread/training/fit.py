"""One training run (``spread-train``, DESIGN §5): a composed ``conf/train.yaml`` → a run folder.

The run folder (``out_dir``, by default ``<paths.runs_dir>/train/<experiment>/<time>``) holds ``.hydra/``
(the composed config), ``checkpoints/`` (:mod:`~spread.training.checkpoints`), ``csv/version_<n>/metrics.csv``
(one version per launch), ``wandb/`` (offline unless ``WANDB_MODE`` says otherwise) and ``metrics.json``
(the final step and logged values). The data module, model and trainer are ``_target_`` nodes of the config
(``conf/data``, ``conf/model``, ``conf/trainer``); :func:`train` adds the loggers
(:func:`spread.tracking.loggers.lightning_loggers`), the callbacks, the final checkpoint and the resume logic.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Callable

import hydra
from lightning.pytorch.callbacks import Callback
from omegaconf import DictConfig, OmegaConf

from spread.io import check_folder_kind
from spread.runtime.threads import set_threads
from spread.training.checkpoints import (CheckpointStep, StopAtStep, StopRequested, atomic_checkpoint_io,
                                         resolve_ckpt_path, save_final_checkpoint, stop_on_interrupt)
from spread.training.determinism import ExactResume
from spread.training.finite import StopOnNonFiniteLoss
from spread.training.trainer_settings import built, check_training_settings, max_time_seconds

log = logging.getLogger("spread.train")


def run_folder(cfg: DictConfig) -> Path:
    """Hydra's output dir inside a Hydra app (also in DDP child processes); ``cfg.out_dir`` otherwise."""
    from hydra.core.hydra_config import HydraConfig

    if HydraConfig.initialized():
        return Path(HydraConfig.get().runtime.output_dir)
    return Path(str(cfg.out_dir))


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


def build_callbacks(cfg: DictConfig, run_dir: Path) -> list:
    """ModelCheckpoint into ``<run folder>/checkpoints``, the training clock (steps, scenes and seconds of each
    checkpoint in ``clock.jsonl``, :mod:`~spread.training.clock`), the training data's digest in every checkpoint
    (:class:`DataDigest`) plus the ``callbacks`` of the config."""
    from spread.training.clock import TrainingClock

    checkpoint = built(lambda: hydra.utils.instantiate(cfg.checkpoint, dirpath=str(run_dir / "checkpoints")),
                       "checkpoint")
    return ([checkpoint, TrainingClock(run_dir), DataDigest()]
            + [built(lambda c=c: hydra.utils.instantiate(c), f"callbacks.{k}")
               for k, c in (cfg.get("callbacks") or {}).items()])


#: The checkpoint key of the training data's content (:class:`DataDigest`).
DATA_DIGEST = "spread_data_sha256"


def data_digest(datamodule) -> str | None:
    """The content of the rooms a datamodule trains and validates on, wherever they lie: the digest of its ``root``'s
    train and val scene files, asset index and statistics (:func:`spread.runtime.fingerprint.dataset_digest`, a
    split or file that is not there without its path); None for a datamodule without a ``root``."""
    from spread.runtime.fingerprint import dataset_digest

    root = getattr(datamodule, "hparams", {}).get("root") if hasattr(datamodule, "hparams") else None
    return dataset_digest(Path(str(root)), ["train", "val"], placeless_markers=True) if root else None


class DataDigest(Callback):
    """Records the training data's content (:func:`data_digest`, computed once when fitting starts) in every
    checkpoint under :data:`DATA_DIGEST`, so a resume compares what the rooms are, wherever they lie
    (:func:`resumed_changes`): rooms added, removed or rewritten in the same folder are a change."""

    def __init__(self):
        self.digest: str | None = None

    def on_fit_start(self, trainer, pl_module) -> None:
        self.digest = data_digest(getattr(trainer, "datamodule", None))

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        if self.digest is not None:
            checkpoint[DATA_DIGEST] = self.digest
        from spread.data.datamodule import wraps_sampler

        checkpoint[TRAINER_SETTINGS] = {**{k: trainer_value(k, getattr(trainer, k, None)) for k in TRAINER_KEYS},
                                        WORLD_SIZE: int(trainer.world_size),
                                        DISTRIBUTED: bool(wraps_sampler(trainer))}


#: Trainer settings a resumed run must keep, recorded in every checkpoint (under :data:`TRAINER_SETTINGS`, by
#: :class:`DataDigest`): how many batches a step takes decides where in the data a resumed run stands, and so do the
#: batches an epoch takes (``limit_train_batches``); the gradient clipping and the precision change every step's
#: update (a resume with another was accepted, and its config rewritten: steps 1–4 in 32-true recorded as
#: bf16-mixed). Keys a checkpoint does not hold (written before they were recorded) are not compared.
TRAINER_KEYS = ("accumulate_grad_batches", "gradient_clip_val", "gradient_clip_algorithm", "precision",
                "limit_train_batches")
TRAINER_SETTINGS = "spread_trainer"
#: Recorded beside :data:`TRAINER_KEYS`: how many processes trained (each a batch per step: the batch of a step and
#: the data order change with it; a one-process checkpoint resumed by Ray Train's two workers failed inside them).
#: Compared where a launch knows it ahead (:func:`planned_world_size`).
WORLD_SIZE = "world_size"
#: Recorded too: whether the training loader was a distributed sampler's (any distributed strategy, one process
#: included) or the resumable single-process order (:mod:`spread.data.order`): the data position one saves, the
#: other cannot take up (a ``spread-train`` checkpoint resumed by one Ray Train worker failed inside it).
DISTRIBUTED = "distributed_sampler"


def trainer_value(key: str, value):
    """A :data:`TRAINER_KEYS` value as recorded and compared: no clipping (None or 0: Lightning clips only at a
    value) is None; the clipping algorithm by name, ``norm`` where it is not set (Lightning's default); the precision
    in Lightning's full spelling (``32-true``); the batches an epoch takes as words (``all``, ``2 batches``, ``0.5 of
    each epoch's batches``)."""
    if key == "gradient_clip_val":
        return float(value) if value else None
    if key == "gradient_clip_algorithm":
        return str(getattr(value, "value", value) or "norm").lower()
    if key == "precision":  # Lightning's short spellings as its trainer names them; none: its default
        text = "32" if value is None else str(value)
        return {"32": "32-true", "64": "64-true", "16": "16-mixed", "bf16": "bf16-mixed"}.get(text, text)
    if key == "limit_train_batches":  # a float is a share, an int a count: 1 and 1.0 differ (JSON would equal them)
        if value is None or (isinstance(value, float) and value == 1.0):
            return "all"
        return f"{value:g} of each epoch's batches" if isinstance(value, float) else \
            f"{int(value)} batch{'es' if int(value) != 1 else ''}"
    return value


#: Hyperparameters a resumed run may change, as they change none of the trained numbers: the model's validation-time
#: sampling, its compilation (the same loss) and its start weights (read by a new run only); the loaders' processes
#: and memory.
RESUMABLE = {"model": ("sample_every_n_epochs", "val_sampler", "val_sample_scenes", "init_from", "compile",
                       "compile_mode", "compile_bucket"),
             "data": ("num_workers", "pin_memory", "persistent_workers")}


def resumed_changes(checkpoint: dict, model, datamodule=None, trainer_settings: dict | None = None) -> list[str]:
    """``model.<key>: held -> now`` / ``data.<key>: ...`` for each hyperparameter this run's model (and datamodule)
    would train with that differs from what the checkpoint was trained with, but :data:`RESUMABLE`; keys the
    checkpoint does not hold (hyperparameters added after it was written, at their defaults) are not compared; what
    the model takes from the data when fitting starts (``data_hparams``: SceneDiffusion's translation bounds, a
    baseline's bounds, categories and size bounds) as the data gives it now; the data by its content (the digest the
    checkpoint recorded, :class:`DataDigest`; for one written before, :func:`moved_data`)."""
    from spread.runtime.fingerprint import described_changes, normalised

    out = []
    for prefix, held, now in (("model", checkpoint.get("hyper_parameters"), getattr(model, "hparams", None)),
                              ("data", checkpoint.get("datamodule_hyper_parameters"),
                               getattr(datamodule, "hparams", None) if datamodule is not None else None)):
        if not held or now is None:
            continue
        held, now = normalised(dict(held)), normalised(dict(now))
        if prefix == "data":  # a checkpoint written before the object limit trained on every room: no limit
            held.setdefault("max_objects", None)
        for key in RESUMABLE[prefix]:
            held.pop(key, None)
            now.pop(key, None)
        if prefix == "model":  # what the model takes from the data when fitting starts: as the data gives it now
            facts = getattr(model, "data_hparams", None)
            given = normalised(facts(datamodule)) if facts is not None and datamodule is not None else {}
            now |= {k: v for k, v in given.items() if now.get(k) is None}
            for key in [k for k, v in now.items() if v is None and held.get(k) is not None]:  # set at fit, unknown
                held.pop(key)
                now.pop(key)
        if prefix == "data" and "root" in held and "root" in now:  # where the data lies is not what it is
            recorded = checkpoint.get(DATA_DIGEST)
            before_root, now_root = str(held.pop("root")), str(now.pop("root"))
            if isinstance(recorded, str):  # the rooms it trained on, by content
                if recorded != data_digest(datamodule):
                    out.append(f"data.root: {before_root!r} -> {now_root!r} (other rooms than it was trained on)")
            else:  # a checkpoint written before the digest: its folder compared, where it still is
                out += moved_data(before_root, now_root)
        out += [f"{prefix}.{change}" for change in described_changes(held, now, held_only=True)]
    held = checkpoint.get(TRAINER_SETTINGS)  # a checkpoint written before this record: not compared
    if isinstance(held, dict) and trainer_settings is not None:
        held, now = dict(held), dict(trainer_settings)
        for key in (WORLD_SIZE, DISTRIBUTED):
            if now.get(key) is None:  # a launch that does not know it ahead (devices: auto)
                held.pop(key, None)
                now.pop(key, None)
        out += [f"trainer.{change}" for change in described_changes(normalised(held), normalised(now),
                                                                     held_only=True)]
    return out


def moved_data(before: str, now: str) -> list[str]:
    """``data.root: before -> now (other rooms)`` when the checkpoint's data folder still exists and holds other
    training or validation rooms than this run's; a moved or copied dataset (or one no longer there) is no change."""
    from spread.runtime.fingerprint import dataset_digest

    a, b = Path(before), Path(now)
    if not a.is_dir() or a.resolve() == b.resolve():
        return []
    if dataset_digest(a, ["train", "val"]) == dataset_digest(b, ["train", "val"]):
        return []
    return [f"data.root: {before!r} -> {now!r} (other rooms)"]


def check_resume_checkpoint(path: Path, model, datamodule=None, trainer_settings: dict | None = None,
                            max_steps=None, max_time: float | None = None) -> str | None:
    """Refuse in one line a ``ckpt_path`` that cannot resume ``model``: unreadable or unsafe (named), or of
    another method, variant or network size (:func:`spread.safe_load.expect_checkpoint`), or trained with other
    settings than this run's (:func:`resumed_changes`: a resumed run restores the checkpoint's optimiser, schedule and
    data order, so a changed learning rate, batch size, seed or dataset would not apply as the new checkpoint would
    record it), or past ``max_steps`` (its step beyond it); a new run from its weights (``model.init_from``) takes new
    settings. Returns the line to print when the run has used its ``max_time`` (seconds) already: Lightning's
    ``Timer`` counts the training time of every launch, so the resume trains nothing — done, as a run at its
    ``max_steps`` is, but said (it printed only success), with the way on."""
    from spread.safe_load import checkpoint_identity, expect_checkpoint

    own = checkpoint_identity({"hyper_parameters": dict(getattr(model, "hparams", {}) or {})})
    checkpoint = expect_checkpoint(path, "ckpt_path", **own)
    changed = resumed_changes(checkpoint, model, datamodule, trainer_settings)
    if changed:
        shown = "; ".join(changed[:4]) + ("; ..." if len(changed) > 4 else "")
        raise ValueError(f"ckpt_path={path}: trained with other settings than this run's ({shown}); resume it with "
                         f"the settings it was trained with, or start a new run from its weights with "
                         f"model.init_from={path} in another out_dir")
    step = checkpoint.get("global_step")
    if isinstance(max_steps, int) and max_steps >= 0 and isinstance(step, int) and step > max_steps:
        raise ValueError(f"ckpt_path={path}: the checkpoint is at step {step}, past trainer.max_steps={max_steps}: the "
                         f"resumed run would train nothing and record a limit that never ran; give trainer.max_steps "
                         f"≥ {step} to train on")
    elapsed = timer_elapsed(checkpoint)
    if max_time is not None and elapsed is not None and elapsed >= max_time:
        return (f"spread-train: {path} has trained for {elapsed:.0f} s, its trainer.max_time of {max_time:.0f} s "
                f"(Lightning counts the time of every launch of a run): nothing to train; give a longer "
                f"trainer.max_time, or null, to train on")
    return None


def timer_elapsed(checkpoint: dict) -> float | None:
    """Seconds of training the checkpoint's Lightning ``Timer`` counted (over every launch), or None without one."""
    import math

    for key, state in (checkpoint.get("callbacks") or {}).items():
        if str(key).split("{")[0] == "Timer" and isinstance(state, dict):
            value = (state.get("time_elapsed") or {}).get("train")
            if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
                return float(value)
    return None


def takes_images(cfg: DictConfig) -> bool:
    """Whether the run's loggers show images (wandb, MLflow; not the CSV files)."""
    from spread.tracking.loggers import as_logger_config

    logger = as_logger_config(cfg.logger)
    return logger.wandb or logger.mlflow


def write_summary(trainer, run_dir: Path, resumed_from: Path | None, skipped: dict | None = None) -> dict:
    """``<run folder>/metrics.json``: final step, epoch, last checkpoint, logged values, the scene files the
    datasets skipped (split → file, error; rank zero only)."""
    from spread.io import write_json_atomic
    from spread.runtime.fingerprint import run_tags

    last = run_dir / "checkpoints" / "last.ckpt"
    summary = {
        "global_step": int(trainer.global_step), "epoch": int(trainer.current_epoch),
        "last_checkpoint": str(last) if last.exists() else None,
        "resumed_from": None if resumed_from is None else str(resumed_from),
        "metrics": {k: (float(v) if math.isfinite(float(v)) else None)  # JSON has no NaN: null, as the evaluation
                    for k, v in trainer.callback_metrics.items() if v.numel() == 1},  # writes a missing value
        "skipped_scene_files": skipped or {},
        "run": {**run_tags(), "world_size": int(trainer.world_size)},  # job id, nodes, git SHA (runtime.fingerprint)
    }
    if trainer.is_global_zero:
        write_json_atomic(run_dir / "metrics.json", summary)
    return summary


HISTORY = ("checkpoints", "metrics.json", "clock.jsonl", "csv")


def one_history(cfg: DictConfig, run_dir: Path, ckpt_path: Path | None) -> None:
    """A run folder holds one training history. Starting a new run (or resuming another run's checkpoint) in a folder
    that holds one is refused, naming the folder and the two ways on: resume it (``ckpt_path=last``) or start over
    with ``fresh=true``, which moves the old history to ``previous/<time>/`` (rank 0 alone decides)."""
    import os
    import shutil
    import time

    if os.environ.get("RANK", "0") != "0":
        return
    held = sorted((run_dir / "checkpoints").glob("*.ckpt")) + sorted(run_dir.glob("hpc_ckpt_*.ckpt"))
    if not held:
        return
    here = {(run_dir / "checkpoints").resolve(), run_dir.resolve()}
    if ckpt_path is not None and ckpt_path.resolve().parent in here:
        if cfg.get("fresh", False):  # it resumed, with no word of fresh
            raise ValueError(f"fresh=true with ckpt_path={cfg.get('ckpt_path')}: fresh starts {run_dir} over (its run "
                             f"moved to previous/<time>), ckpt_path resumes that run; give one of the two")
        return
    if not cfg.get("fresh", False):
        raise SystemExit(f"spread-train: {run_dir} holds a training run already ({held[-1].name}): resume it with "
                         f"ckpt_path=last, or start over with fresh=true (moves it to {run_dir / 'previous'}/<time>)")
    aside = run_dir / "previous" / time.strftime("%Y-%m-%d_%H-%M-%S")
    aside.mkdir(parents=True, exist_ok=True)
    for name in [*HISTORY, *(p.name for p in run_dir.glob("hpc_ckpt_*.ckpt"))]:
        if (run_dir / name).exists():
            shutil.move(str(run_dir / name), str(aside / name))
    log.warning("fresh=true: the run that was in %s is now in %s", run_dir, aside)


def mark_attempt_started() -> None:
    """A launcher's attempt (jobs/torchrun.sh: ``SPREAD_ATTEMPT_MARK``) is marked started once every process runs,
    so the launcher's next launch counts a new attempt (jobs/env.sh ``spread_attempt``)."""
    import os

    mark = os.environ.get("SPREAD_ATTEMPT_MARK")
    if mark:
        Path(mark).parent.mkdir(parents=True, exist_ok=True)
        Path(mark).touch()


def feed_the_device(trainer, datamodule) -> None:
    """On a GPU, batches come from pinned memory (asynchronous copies), built by loader processes beside the training
    loop when ``data.num_workers`` is null (the default: :func:`~spread.data.datamodule.loader_workers`, up to 4 a
    training process, kept across epochs; on a CPU trainer none, as the training uses the cores); an explicit
    ``data.num_workers=0`` gets a warning that loading runs in the training loop (``perf/data_wait_share`` shows its
    cost)."""
    accelerator = type(getattr(trainer, "accelerator", None)).__name__.lower()
    if "cuda" not in accelerator and "gpu" not in accelerator:
        return
    if hasattr(datamodule, "pin_memory"):
        datamodule.pin_memory = True
    if getattr(datamodule, "auto_workers", False):
        from spread.data.datamodule import loader_workers

        datamodule.use_workers(loader_workers(int(getattr(trainer, "num_devices", 1) or 1)))
    if getattr(datamodule, "num_workers", 1) == 0:
        log.warning("training on a GPU with data.num_workers=0: batches are built in the training loop; leave "
                    "data.num_workers unset (null: up to 4 loader processes beside a GPU) or give a count")


def check_accelerator(cfg: DictConfig, override: str | None = None) -> None:
    """``trainer.accelerator=gpu`` (``trainer=gpu``) in a process that sees no CUDA device is refused by name before
    any work (Lightning's "No supported gpu backend found!" came from inside Hydra's instantiate, after the data and
    the model were built). Checked where training runs: a launcher's workers on GPU nodes check their own;
    ``override``: the accelerator a launcher gives the Trainer instead (Ray Train's ``use_gpu``)."""
    accelerator = str(override or OmegaConf.select(cfg, "trainer.accelerator", default="") or "")
    if accelerator in ("gpu", "cuda"):
        import torch

        if not torch.cuda.is_available():
            raise ValueError(f"trainer.accelerator={accelerator} (trainer=gpu): this process sees no CUDA device "
                             f"(torch.cuda.is_available() is False); use trainer=cpu")


def trainer_settings_of(cfg: DictConfig, overrides: dict | None = None) -> dict:
    """The :data:`TRAINER_KEYS` settings a run's trainer will hold (Lightning's defaults where the config is silent),
    and its :data:`WORLD_SIZE` (:func:`planned_world_size`; ``overrides``: a launcher's Trainer arguments)."""
    defaults = {"accumulate_grad_batches": 1}
    return {**{k: trainer_value(k, OmegaConf.select(cfg, f"trainer.{k}", default=defaults.get(k))) for k in TRAINER_KEYS},
            WORLD_SIZE: planned_world_size(cfg, overrides), DISTRIBUTED: planned_distributed(cfg, overrides)}


def planned_distributed(cfg: DictConfig, overrides: dict | None = None) -> bool | None:
    """Whether a launch of ``cfg`` trains under a distributed sampler (:data:`DISTRIBUTED`), where the config says
    it ahead: Ray Train's driver always; a ``ddp``/``fsdp``/``deepspeed`` strategy (unless
    ``use_distributed_sampler`` is off); ``auto`` with more than one process; None where it cannot be told
    (``devices: auto``; a launcher's worker, ``overrides``)."""
    if OmegaConf.select(cfg, "ray_train") is not None:
        return True
    if overrides:
        return None
    if OmegaConf.select(cfg, "trainer.use_distributed_sampler", default=True) is False:
        return False
    strategy = str(OmegaConf.select(cfg, "trainer.strategy", default="auto") or "auto").lower()
    if strategy.startswith(("ddp", "fsdp", "deepspeed")):
        return True
    world = planned_world_size(cfg)
    if strategy not in ("auto", "single_device") or world is None:
        return None
    return world > 1


def planned_world_size(cfg: DictConfig, overrides: dict | None = None) -> int | None:
    """How many processes a launch of ``cfg`` trains in, where the config says it ahead: Ray Train's
    ``ray_train.num_workers`` (its driver); else ``trainer.devices`` (a count or a list) × ``trainer.num_nodes``;
    None where a launcher or Lightning decides (``devices: auto``, ``-1``; a launcher's own ``devices`` in
    ``overrides``: a Ray Train worker)."""
    from spread.checks import is_whole

    workers = OmegaConf.select(cfg, "ray_train.num_workers")
    if workers is not None:
        return int(workers) if is_whole(workers) else None
    if overrides and "devices" in overrides:
        return None
    devices = OmegaConf.select(cfg, "trainer.devices", default=1)
    nodes = OmegaConf.select(cfg, "trainer.num_nodes", default=1)
    if isinstance(devices, str) and devices.strip().isdigit():
        devices = int(devices)
    elif not isinstance(devices, (int, str)) and devices is not None:
        try:
            devices = len(devices)  # a list of device indices
        except TypeError:
            return None
    if not (is_whole(devices) and is_whole(nodes)) or devices < 1 or nodes < 1:
        return None
    return int(devices) * int(nodes)


def check_start(cfg: DictConfig, run_dir: Path) -> None:
    """What a training launch checks before it records its config or starts any work (``spread-train-ray``'s driver,
    before Ray starts; ``spread-train`` within :func:`train`): the ``trainer.*`` values are Trainer arguments
    (:func:`~spread.training.trainer_settings.check_training_settings`: seed, threads, Trainer arguments), the folder holds one history
    (:func:`one_history`) and a resumed checkpoint was trained with this run's settings
    (:func:`check_resume_checkpoint`) and the data has scenes to train (and validate) on (the data module's
    ``check_fit``: else every worker would raise it)."""
    check_training_settings(cfg)
    check_folder_kind(run_dir, "spread-train", {"training run"})
    ckpt_path = resolve_ckpt_path(cfg, run_dir)
    one_history(cfg, run_dir, ckpt_path)
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.check_fit(trainer_validates(cfg.trainer))
    if ckpt_path is not None:
        check_resume_checkpoint(ckpt_path, hydra.utils.instantiate(cfg.model), datamodule,
                                trainer_settings_of(cfg),
                                max_steps=OmegaConf.select(cfg, "trainer.max_steps"),
                                max_time=max_time_seconds(OmegaConf.select(cfg, "trainer.max_time")))


def trainer_validates(trainer_cfg, overrides: dict | None = None) -> bool:
    """Whether a trainer of this config (``cfg.trainer``, ``overrides`` winning) runs validation, asked before the
    trainer exists (:func:`spread.data.splits.runs_validation`, Lightning's default ``limit_val_batches`` 1.0)."""
    from spread.data.splits import runs_validation

    values = {**dict(trainer_cfg or {}), **dict(overrides or {})}
    return runs_validation(values.get("limit_val_batches", 1.0))


def stopped(stopper: StopAtStep) -> BaseException:
    """What a run stopped by a signal raises: KeyboardInterrupt for Ctrl-C (the command exits 130), ``SystemExit(143)``
    for SIGTERM (128 + 15, what a scheduler reads as terminated; :func:`spread.runtime.ray.terminated`)."""
    from spread.runtime.ray import TERMINATED

    return SystemExit(TERMINATED) if stopper.asked == "SIGTERM" else KeyboardInterrupt()


def train(cfg: DictConfig, run_dir: Path | None = None, *, trainer_overrides: dict | None = None,
          extra_callbacks: list | None = None, prepare: Callable | None = None,
          resume_from: Path | None = None, before_work: Callable[[], None] | None = None) -> dict:
    """Fit the configured model on the configured data into ``run_dir``; returns the summary.

    The keyword arguments let another launcher run this same code (Ray Train,
    :mod:`spread.training.ray_train`): ``trainer_overrides`` replace Trainer arguments of ``cfg.trainer``
    (strategy, plugins, devices, ...), ``extra_callbacks`` join the config's, ``prepare(trainer) -> trainer``
    runs before ``fit``, and ``resume_from`` (a checkpoint file of this run: a launcher's restart after a failure) wins
    over ``ckpt_path``; ``before_work()`` runs once
    the checks passed (the command records its config there, so a refused launch leaves the folder's record as it
    was)."""
    import lightning as L

    from spread.tracking.loggers import as_logger_config, lightning_loggers
    from spread.training.monitors import monitors

    check_training_settings(cfg, trainer_overrides)
    check_accelerator(cfg, (trainer_overrides or {}).get("accelerator"))
    run_dir = Path(run_dir) if run_dir is not None else run_folder(cfg)
    check_folder_kind(run_dir, "spread-train", {"training run"})
    run_dir.mkdir(parents=True, exist_ok=True)
    from spread.runtime.quiet import silence_known_noise

    silence_known_noise()
    route_lightning_logs()
    set_threads(cfg.get("threads"))
    L.seed_everything(int(cfg.seed), workers=True, verbose=False)
    ckpt_path = Path(resume_from) if resume_from is not None else resolve_ckpt_path(cfg, run_dir)
    if resume_from is None:  # a launcher's restart of this very run (Ray Train's) continues its own history
        one_history(cfg, run_dir, ckpt_path)
    mark_attempt_started()
    resuming_here = ckpt_path is not None and ckpt_path.resolve().parent == (run_dir / "checkpoints").resolve()
    datamodule = hydra.utils.instantiate(cfg.data)
    datamodule.check_fit(trainer_validates(cfg.trainer, trainer_overrides))  # before a logger opens a run
    model = hydra.utils.instantiate(cfg.model)
    used_up = None  # the line saying a resumed run has used its max_time already
    if ckpt_path is not None:  # the file is read safely and must be this run's kind of model, before fit
        used_up = check_resume_checkpoint(ckpt_path, model, datamodule, trainer_settings_of(cfg, trainer_overrides),
                                          max_steps=OmegaConf.select(cfg, "trainer.max_steps"),
                                          max_time=max_time_seconds(OmegaConf.select(cfg, "trainer.max_time")))
    callbacks = build_callbacks(cfg, run_dir)  # a checkpoint.* value Lightning refuses: before the record
    if before_work is not None:
        before_work()
    newest = CheckpointStep()
    stopper = StopAtStep(run_dir / "checkpoints" / "last.ckpt")
    overrides = dict(trainer_overrides or {})
    plugins = [atomic_checkpoint_io(), *(overrides.pop("plugins", None) or [])]
    loggers = lightning_loggers(as_logger_config(cfg.logger), run_dir, str(cfg.experiment_name),
                                [str(t) for t in cfg.tags], OmegaConf.to_container(cfg, resolve=True), resuming_here)
    trainer = hydra.utils.instantiate(cfg.trainer, default_root_dir=str(run_dir), logger=loggers or False,
                                      callbacks=callbacks + [newest, stopper, ExactResume(int(cfg.seed)), StopOnNonFiniteLoss(),
                                                                                 *(monitors(cfg.get("renders") if takes_images(cfg) else None) if loggers else []),
                                                                                 *(extra_callbacks or [])],
                                      plugins=plugins, **overrides)
    if prepare is not None:
        trainer = prepare(trainer)
    feed_the_device(trainer, datamodule)
    if ckpt_path is not None and trainer.is_global_zero:
        print(f"spread-train: resuming {ckpt_path}", flush=True)
        if used_up:
            print(used_up, flush=True)
    try:
        with stop_on_interrupt(stopper):
            trainer.fit(model, datamodule=datamodule, ckpt_path=None if ckpt_path is None else str(ckpt_path))
    except StopRequested as stop:  # Ctrl-C / SIGTERM: the step saved; no summary (the run is not finished)
        if trainer.is_global_zero:
            print(f"spread-train: interrupted ({stopper.asked}) at step {stop.args[0]}: {stopper.last} holds it; "
                  f"relaunch with ckpt_path=last to go on", flush=True)
        raise stopped(stopper) from None
    except SystemExit:  # a second signal: Lightning's shutdown exits 1; a study must stop, not go on
        if stopper.asked:
            raise stopped(stopper) from None
        raise
    save_final_checkpoint(trainer, run_dir, newest)
    skipped = datamodule.skipped_files() if hasattr(datamodule, "skipped_files") else {}
    summary = write_summary(trainer, run_dir, ckpt_path, skipped)
    if trainer.is_global_zero:
        resumed = f", resumed from {summary['resumed_from']}" if summary["resumed_from"] else ""
        print(f"run folder {run_dir}: step {summary['global_step']}, epoch {summary['epoch']}, "
              f"checkpoint {summary['last_checkpoint']}{resumed}")
    return summary
