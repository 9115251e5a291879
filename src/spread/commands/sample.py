"""``spread-sample``'s body: one sampling run, and with ``evaluate=true`` its evaluation into the same run folder
(one wandb run holds both; a sweep point), logged, and its console summary."""

from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig

from spread.commands.common import failed_on_error, plain, record_config
from spread.configs import to_object


def evaluation_after_sampling(command):
    """The :class:`~spread.evaluation.EvaluationConfig` of ``spread-sample evaluate=true``: the run's scenes
    against the dataset's ``evaluation.reference_split``, results beside them in ``out_dir``, under the object limit
    the sampling applied to its graphs (so the evaluation leaves out no scene the sampling made)."""
    from spread.evaluation import EvaluationConfig

    ev = command.evaluation
    return EvaluationConfig(
        scenes=str(Path(command.out_dir) / "scenes"), reference=command.data.root, out_dir=command.out_dir,
        reference_split=ev.reference_split, chunk_size=ev.chunk_size, resume=command.resume,
        retry_failed=ev.retry_failed, renders=ev.renders, progress=command.progress, protocol=ev.protocol,
        fid=ev.fid, ray=command.ray,  # the sampling's own limit (≤ 0: none): the evaluation leaves out no scene
        max_objects=None if command.max_objects is None else max(0, int(command.max_objects)))


def experiment_of(command) -> str:
    """The experiment (wandb group, MLflow experiment) of a sampling command: ``experiment_name``, and the sweep
    folder's name after it when a sweep's folder is not named so (two launches of one sweep file into
    different folders are two experiments)."""
    name = str(command.experiment_name)
    folder = Path(str(command.sweep_dir)).name if command.sweep_dir else None
    return name if not folder or folder == name else f"{name}/{folder}"


def sampling_continuation(command, config: dict):
    """Whether this launch continues the folder's tracker runs (:mod:`spread.tracking.continuation`): the
    identity of its results is the sweep point's (:func:`spread.runtime.fingerprint.point_identity`: the sampling
    identity, the samples per graph and, with ``evaluate=true``, the evaluation's), beside the command's ``config``."""
    from spread.runtime.fingerprint import point_identity
    from spread.tracking.continuation import Continuation

    return Continuation(command.out_dir, "sample", lambda: point_identity(command), command.resume, config)


def sample(cfg: DictConfig, log: bool = True, overrides: list[str] | None = None):
    """``spread-sample``: sample (then, with ``evaluate=true``, evaluate) into ``cfg.out_dir``; returns
    (:class:`~spread.sampling.SamplingResult`, :class:`~spread.evaluation.EvaluationResult` or None). A
    finished sweep point (``evaluate=true``, ``resume=true``, ``metrics.json`` there) is left as it is
    and (None, None) returned when its fingerprint matches, else redone (:mod:`spread.experiments.points`).
    ``log=False``: no wandb or MLflow run (the ablation logs its table instead)."""
    from spread.io import run_lock

    command = to_object(cfg)
    # the lock before the point's record and the trackers: a refused second run writes neither
    with run_lock(command.out_dir, "spread-sample", nest=True):
        return _sample(cfg, command, log, overrides)


def _sample(cfg: DictConfig, command, log: bool, overrides: list[str] | None):
    from spread.tracking import mlflow_store as mlflow_log
    from spread.sampling import run_sampling
    from spread.tracking.sampling_mlflow import sampling_run_tags
    from spread.tracking.sampling_wandb import log_sampling, open_sampling_run

    before_work = record_config(cfg, command.out_dir, overrides)
    if command.evaluate:  # a sweep point: re-used only when its fingerprint matches (experiments.points)
        from spread.experiments.points import check_point, finish_point, start_point

        point = check_point(command, command.out_dir, command.resume)
        if point.reuse:
            print(f"{command.out_dir}: finished earlier with the same fingerprint, re-used")
            return None, None
        from spread.evaluation.run import check_fid

        check_fid(command.evaluation.fid)  # a backbone that cannot load: refused before the sampling, not after
        if point.reason:  # sampling and evaluation then keep what their own fingerprints still match
            print(f"{command.out_dir}: redone ({point.reason})")
        record = before_work

        def before_work():
            record()
            start_point(command.out_dir, point)
    started = time.perf_counter()
    experiment = experiment_of(command)
    again = sampling_continuation(command, plain(cfg))
    wandb_run = open_sampling_run(command, plain(cfg), experiment, again.wandb_id()) \
        if log and command.logger.wandb else None
    with failed_on_error(wandb_run):
        with mlflow_log.tracked(command.logger if log else None, "sample", command.out_dir, plain(cfg), experiment,
                                tags=lambda: sampling_run_tags(command), continuation=again) as run:
            result = run_sampling(command, before_work=again.recorded(before_work, run, wandb_run))
            if run is not None:
                mlflow_log.log_sampling(run, result.manifest)
            evaluation = None
            if command.evaluate:
                from spread.evaluation import run_evaluation

                evaluation = run_evaluation(evaluation_after_sampling(command))
                finish_point(command.out_dir, round(time.perf_counter() - started, 3))
                if run is not None:
                    mlflow_log.log_evaluation(run, evaluation.metrics, evaluation.out_dir, evaluation.renders)
    if wandb_run is not None:
        log_sampling(result.manifest, command.out_dir, plain(cfg), command.logger, group=experiment,
                     evaluation=evaluation, run=wandb_run)
    return result, evaluation


def print_sampling_summary(result) -> None:
    m = result.manifest
    per_batch = "" if m["seconds_per_batch"] is None else f", {m['seconds_per_batch']:.2f} s per batch"
    print(f"{result.out_dir / 'scenes'}: {m['samples']} scenes of {m['graphs']} graphs "
          f"({m['written_this_run']} written now, {m['resumed']} already there; {m['seconds']:.1f} s{per_batch}; "
          f"{m['runner']['mode']}, {m['runner']['workers']} worker(s))")
