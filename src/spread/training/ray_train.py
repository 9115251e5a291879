"""Ray Train for ``spread-train``: the same config, code and run folder, on Ray workers (DESIGN §7).

    spread-train-ray experiment=quick data.root=/shared/rooms ray_train.num_workers=4
    spread-train-ray ... ray_train.address=auto ray_train.use_gpu=true   # a Ray cluster
    spread-train-ray ... ckpt_path=last out_dir=<its run folder>         # resume

A Hydra app over ``conf/train.yaml`` (every ``spread-train`` override works) with ``trainer=ray`` chosen
unless the command line names a trainer: ``conf/trainer/ray.yaml`` adds the ``ray_train`` block (workers,
GPUs, CPUs per worker, address, failures, storage). The driver starts or joins Ray
(:func:`~spread.runtime.ray.ray_session`) and runs a ``ray.train.torch.TorchTrainer`` whose
workers each call :func:`spread.training.fit.train` — the same data module, model, loggers, checkpoints
(``<run folder>/checkpoints``, written by rank 0), final checkpoint and ``metrics.json`` as
``spread-train`` — with Lightning's DDP replaced by Ray's pieces: ``RayDDPStrategy`` (devices from Ray),
``RayLightningEnvironment`` (ranks from Ray), ``prepare_trainer`` and ``RayTrainReportCallback`` (a Ray
checkpoint at every epoch end, into ``ray_train.storage_path``). Gloo on CPUs, NCCL on GPUs.

Resume: a fresh launch follows ``ckpt_path`` exactly as ``spread-train`` does. When Ray restarts the
worker group after a failure (``ray_train.max_failures``), the workers resume from Ray's newest reported
checkpoint instead. The run folder and the storage path must be on a filesystem every node sees.

Ray and Lightning are imported inside the functions.
"""

from __future__ import annotations

import contextlib
import os
import sys
from dataclasses import dataclass
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

#: Name of the config block that holds the Ray Train settings (``conf/trainer/ray.yaml``).
BLOCK = "ray_train"


@dataclass(frozen=True)
class RayTrainSettings:
    """address: None (private Ray on this machine) or "auto"/HOST:PORT (join); num_cpus: CPUs of a private
    Ray; num_workers: training processes; use_gpu: one GPU each; cpus_per_worker: CPUs each reserves;
    max_failures: worker-group restarts; storage_path: Ray Train's store (None: <run folder>/ray_train);
    num_to_keep: Ray checkpoints kept; log_to_driver: echo worker output."""

    address: str | None = None
    num_cpus: int | None = None
    num_workers: int = 2
    use_gpu: bool = False
    cpus_per_worker: float = 1.0
    max_failures: int = 0
    storage_path: str | None = None
    num_to_keep: int | None = 2
    log_to_driver: bool = True

    def __post_init__(self) -> None:
        """Each setting by key (``ray_train.<key>=<value>: expected …``): ``num_workers=0`` trained in the driver
        outside Ray Train's store, ``cpus_per_worker=0`` failed inside Ray after it started, ``num_to_keep=0``
        kept no checkpoint."""
        import math

        from spread.checks import true_or_false, whole_number

        whole_number(self.num_workers, f"{BLOCK}.num_workers", 1)
        whole_number(self.num_cpus, f"{BLOCK}.num_cpus", 1, null="all of this machine's")
        whole_number(self.max_failures, f"{BLOCK}.max_failures", -1, note="(-1: restart without end)")
        whole_number(self.num_to_keep, f"{BLOCK}.num_to_keep", 1, null="every checkpoint")
        cpus = self.cpus_per_worker
        if isinstance(cpus, bool) or not isinstance(cpus, (int, float)) or not math.isfinite(cpus) or cpus <= 0:
            raise ValueError(f"{BLOCK}.cpus_per_worker={cpus!r}: expected a number > 0 (CPUs each worker reserves)")
        true_or_false(self.use_gpu, f"{BLOCK}.use_gpu")
        true_or_false(self.log_to_driver, f"{BLOCK}.log_to_driver")
        for key in ("address", "storage_path"):
            value = getattr(self, key)
            if value is not None and not (isinstance(value, str) and value):
                raise ValueError(f"{BLOCK}.{key}={value!r}: expected a text or null")


def ray_train_settings(cfg: DictConfig) -> RayTrainSettings:
    """The ``ray_train`` block of a composed config as :class:`RayTrainSettings`, each key checked
    (:meth:`RayTrainSettings.__post_init__`); a key it does not know is named with the known ones. Asked on the driver
    before the config is recorded or Ray starts."""
    import dataclasses

    if BLOCK not in cfg:
        raise SystemExit("spread ray_train: the config has no ray_train block; use trainer=ray")
    values = OmegaConf.to_container(cfg[BLOCK], resolve=True)
    known = [f.name for f in dataclasses.fields(RayTrainSettings)]
    unknown = [k for k in values if k not in known]
    if unknown:
        raise ValueError(f"{BLOCK}.{unknown[0]}: not a Ray Train setting (known: {', '.join(known)})")
    return RayTrainSettings(**values)


def split_config(cfg: DictConfig, run_dir: Path) -> tuple[dict, RayTrainSettings]:
    """(the train config as a resolved plain dict, without the ``ray_train`` block and with ``out_dir`` =
    ``run_dir``; the settings). Resolved here, once, so that every worker sees the same values
    (``${now:...}`` in particular)."""
    settings = ray_train_settings(cfg)
    container = OmegaConf.to_container(cfg, resolve=False)
    container.pop(BLOCK)
    container["out_dir"] = str(run_dir)
    resolved = OmegaConf.to_container(OmegaConf.create(container), resolve=True)
    return resolved, settings


#: Where, under the run folder, a worker writes its epoch-end checkpoint before Ray copies it to its store (Ray's
#: callback wrote it to the system's temporary folder, outside the run, and left a folder there per rank and launch:
#: after a Ctrl-C holding a whole checkpoint); removed when the worker's training ends.
SCRATCH = ".epoch_checkpoints"


def report_callback(run_dir: Path | None = None):
    """``RayTrainReportCallback`` that leaves :class:`~spread.training.checkpoints.CheckpointStep` as it was: its
    epoch-end checkpoint goes to Ray's store, not to ``checkpoints/last.ckpt``, so it must not make the final
    save (:func:`~spread.training.checkpoints.save_final_checkpoint`) believe ``last.ckpt`` already holds the
    final state. ``run_dir``: its scratch folder goes under ``<run_dir>/ray_train/`` (:data:`SCRATCH`)."""
    import shutil

    import ray.train
    from ray.train.lightning import RayTrainReportCallback

    from spread.training.checkpoints import CheckpointStep

    class ReportCallback(RayTrainReportCallback):
        def __init__(self):
            super().__init__()
            if run_dir is not None:
                rank = ray.train.get_context().get_world_rank()
                self.tmpdir_prefix = str(Path(run_dir) / "ray_train" / SCRATCH / f"rank{rank}")

        def on_train_epoch_end(self, trainer, pl_module) -> None:
            steps = [c for c in trainer.callbacks if isinstance(c, CheckpointStep)]
            before = [c.step for c in steps]
            super().on_train_epoch_end(trainer, pl_module)
            for c, step in zip(steps, before):
                c.step = step

        def teardown(self, trainer, pl_module, stage: str) -> None:
            shutil.rmtree(self.tmpdir_prefix, ignore_errors=True)
            if run_dir is not None:  # the last rank out removes the scratch folder itself
                with contextlib.suppress(OSError):
                    (Path(run_dir) / "ray_train" / SCRATCH).rmdir()

    return ReportCallback()


def train_worker(config: dict) -> dict:
    """The training function of every Ray Train worker: :func:`spread.training.fit.train` with Ray's strategy,
    environment and report callback; returns the run summary (``Result.return_value`` from rank 0)."""
    import ray.train
    from ray.train.lightning import RayDDPStrategy, RayLightningEnvironment, RayTrainReportCallback, prepare_trainer

    from spread.training.fit import train

    cwd = config.get("cwd")
    if cwd and Path(cwd).is_dir():  # the driver's: a relative data.root, ckpt_path or init_from means the same
        os.chdir(cwd)  # there (a Ray worker starts in its session's folder: "no scene files in demo_out/data/train")
    cfg = OmegaConf.create(config["cfg"])
    run_dir = Path(config["run_dir"])

    def run(resume_from: Path | None) -> dict:
        overrides = {"strategy": RayDDPStrategy(), "plugins": [RayLightningEnvironment()], "devices": "auto",
                     "num_nodes": 1, "accelerator": "gpu" if config["use_gpu"] else "cpu"}
        summary = train(cfg, run_dir, trainer_overrides=overrides, extra_callbacks=[report_callback(run_dir)],
                        prepare=prepare_trainer, resume_from=resume_from)
        return {**summary, "world_size": ray.train.get_context().get_world_size()}

    checkpoint = ray.train.get_checkpoint()  # set when Ray restarted this launch's workers after a failure
    if checkpoint is None:
        return run(None)
    with checkpoint.as_directory() as folder:  # the newer of Ray's epoch-end checkpoint and the run's last.ckpt
        return run(newest_checkpoint([Path(folder) / RayTrainReportCallback.CHECKPOINT_NAME,
                                      run_dir / "checkpoints" / "last.ckpt"]))


def newest_checkpoint(paths: list[Path]) -> Path:
    """The checkpoint file of ``paths`` at the highest ``global_step`` (read safely; the first on a tie; files that are
    not there or do not read are passed over): Ray's epoch-end checkpoint can be older than the run's periodic
    ``last.ckpt``, which resuming from would lose."""
    from spread.safe_load import load_checkpoint

    best, step = paths[0], -1
    for path in paths:
        try:
            held = int(load_checkpoint(path).get("global_step", -1)) if path.is_file() else -1
        except Exception:  # noqa: BLE001 - a torn or foreign file is no candidate
            held = -1
        if held > step:
            best, step = path, held
    return best


def run_ray_train(cfg: DictConfig, run_dir: Path):
    """Train ``cfg`` (a composed ``conf/train.yaml`` with ``trainer=ray``) on Ray Train into ``run_dir``;
    returns Ray Train's ``Result`` (``return_value``: rank 0's summary; ``checkpoint``: the newest Ray
    checkpoint, a folder with ``checkpoint.ckpt``)."""
    import shutil
    import signal
    import threading

    from ray.train import CheckpointConfig, FailureConfig, RunConfig, ScalingConfig

    from spread.runtime.ray import RaySettings, ray_session

    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    container, settings = split_config(cfg, run_dir)
    resources = {"CPU": float(settings.cpus_per_worker)}
    if settings.use_gpu:
        resources["GPU"] = 1.0
    storage = Path(settings.storage_path or run_dir / "ray_train").resolve()
    name = launch_name(run_dir)
    trainer = (interruptible_trainer() if settings.address else private_cluster_trainer())(
        train_worker,
        train_loop_config={"cfg": container, "run_dir": str(run_dir), "use_gpu": bool(settings.use_gpu),
                           "cwd": os.getcwd()},
        scaling_config=ScalingConfig(num_workers=int(settings.num_workers), use_gpu=bool(settings.use_gpu),
                                     resources_per_worker=resources),
        run_config=RunConfig(name=name, storage_path=str(storage),
                             failure_config=FailureConfig(max_failures=int(settings.max_failures)),
                             checkpoint_config=CheckpointConfig(num_to_keep=settings.num_to_keep)),
    )
    ray_settings = RaySettings(address=settings.address, num_cpus=settings.num_cpus,
                               log_to_driver=settings.log_to_driver)
    previous = signal.getsignal(signal.SIGINT)
    try:
        with ray_session(ray_settings, owner=run_dir):
            result = trainer.fit()
    except SystemExit:  # Ray's handler exits from inside fit on a Ctrl-C it could not pass on
        if trainer.interrupted:
            keep_newest_reported(run_dir, storage / name)
            raise KeyboardInterrupt from None
        raise
    finally:
        if threading.current_thread() is threading.main_thread():  # Ray's handler outlived its run
            signal.signal(signal.SIGINT, previous)
        shutil.rmtree(run_dir / "ray_train" / SCRATCH, ignore_errors=True)  # left by workers an abort stopped
    if trainer.interrupted:
        keep_newest_reported(run_dir, storage / name)
        raise KeyboardInterrupt
    if result.error is not None:
        raise worker_user_error(result.error) or result.error
    return result


def keep_newest_reported(run_dir: Path, launch: Path) -> Path | None:
    """After a Ctrl-C aborted the workers: this launch's newest epoch-end checkpoint in Ray's store becomes the run
    folder's ``checkpoints/last.ckpt`` when it is further on (written atomically), so ``ckpt_path=last`` goes on from
    it (the workers write ``last.ckpt`` every ``checkpoint.every_n_train_steps`` and at the end only, and a relaunch
    reads ``last.ckpt`` alone: an early Ctrl-C left none). Returns the checkpoint kept (None: none newer)."""
    import logging
    import shutil

    from spread.io import atomic_path

    last = run_dir / "checkpoints" / "last.ckpt"
    reported = sorted(Path(launch).glob("checkpoint_*/checkpoint.ckpt"))
    newest = newest_checkpoint([last, *reported]) if reported else last
    if newest == last or not newest.is_file():
        return None
    with atomic_path(last) as tmp:
        shutil.copyfile(newest, tmp)
    logging.getLogger("spread.train").warning("interrupted: %s (Ray's newest epoch-end checkpoint) is now %s; "
                                              "ckpt_path=last goes on from it", newest, last)
    return newest


def launch_name(run_dir: Path) -> str:
    """This launch's Ray Train run name, its own: Ray Train restores a run of the same name from its storage, so
    a relaunch named as the folder started from the previous launch's last epoch-end checkpoint (refused as another
    history, or, with ``fresh=true``, resumed instead of started over). A relaunch goes on from the run folder's
    ``last.ckpt`` (``ckpt_path=last``); Ray restores only within a launch (``ray_train.max_failures``)."""
    import os
    import time

    return f"{run_dir.name}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"


def worker_user_error(error: BaseException) -> BaseException | None:
    """The bad setting or input (a ``ValueError``, ``FileNotFoundError``, ``PermissionError``: what the console
    scripts report in one line) a training worker raised, found through Ray's wrappers: Ray Train v1's
    ``TrainingFailedError`` and ``RayTaskError`` (whose dual classes are skipped; their ``cause`` or ``__cause__``),
    Ray Train v2's ``WorkerGroupError`` (``worker_failures``, lowest rank first), ``ControllerError``
    (``controller_failure``) and ``UserExceptionWithTraceback`` (the worker's own exception); None for any other
    failure."""
    seen: set[int] = set()
    waiting = [error]
    while waiting:
        error = waiting.pop(0)
        if error is None or id(error) in seen:
            continue
        seen.add(id(error))
        if isinstance(error, (ValueError, FileNotFoundError, PermissionError)) and \
                "ray" not in type(error).__module__.split(".")[0] and "RayTaskError" not in type(error).__name__:
            return error
        failures = getattr(error, "worker_failures", None)
        if isinstance(failures, dict):
            waiting += [failures[rank] for rank in sorted(failures)]
        for link in ("cause", "_base_exc", "controller_failure"):  # RayTaskError's, v2's; the others chain as __cause__
            inner = getattr(error, link, None)
            if isinstance(inner, BaseException):
                waiting.append(inner)
        waiting.append(error.__cause__)
    return None


def private_cluster_trainer():
    """``TorchTrainer`` for a Ray the command starts itself (``ray_train.address=null``) and stops at its end, taking
    its placement groups with it: without Ray Train's detached ``PlacementGroupCleaner`` actor, which exists to
    free them after a controller dies on a *shared* cluster, and which, on a Ray started without its dashboard,
    polls a State API that is not there and prints an alarming ``ConnectionError`` traceback (often when other
    Ray instances run on the host). On a cluster (``address`` set) the plain ``TorchTrainer`` keeps it
    (:func:`interruptible_trainer` both)."""
    class PrivateClusterTorchTrainer(interruptible_trainer()):
        def _create_default_callbacks(self):
            return [c for c in super()._create_default_callbacks()
                    if type(c).__name__ != "PlacementGroupCleanerCallback"]

    return PrivateClusterTorchTrainer


def interruptible_trainer():
    """``TorchTrainer`` that notes a Ctrl-C (``interrupted``): Ray Train's own SIGINT handler aborts the run and
    makes ``fit`` end as if nothing happened, or exit 0 or 1 from inside, so the command ended with status 1 and
    no word; noted, :func:`run_ray_train` ends it as every command ends on Ctrl-C (status 130, one line)."""
    import signal

    from ray.train.torch import TorchTrainer

    class InterruptibleTorchTrainer(TorchTrainer):
        interrupted = False

        def _register_sigint_handler(self, controller):
            super()._register_sigint_handler(controller)
            ray_handler = signal.getsignal(signal.SIGINT)

            def noted(signum, frame):
                self.interrupted = True
                if callable(ray_handler):
                    ray_handler(signum, frame)

            signal.signal(signal.SIGINT, noted)

    return InterruptibleTorchTrainer


def with_default_trainer(argv: list[str]) -> list[str]:
    """``argv`` with ``trainer=ray`` unless it names a trainer already (``trainer=...``, not ``trainer.x=``),
    put before the first override (Hydra reads its flags, ``-m``, ``--cfg job``, only before the overrides)."""
    names = [a.split("=", 1)[0].lstrip("+~") for a in argv[1:] if "=" in a]
    if "trainer" in names:
        return list(argv)
    first = next((i for i, a in enumerate(argv) if i > 0 and "=" in a), len(argv))
    return [*argv[:first], "trainer=ray", *argv[first:]]
