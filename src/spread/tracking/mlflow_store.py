"""Runs in a local MLflow store (``logger=mlflow``; conventions: :mod:`spread.tracking.loggers`).

One store holds every command's runs: by default the SQLite file ``<paths.runs_dir>/mlflow.db`` with the
artifacts beside it in ``<paths.runs_dir>/mlartifacts/<experiment>``; ``logger.tracking_uri`` points
elsewhere (another file, or a shared ``http://`` server on a cluster). ``spread-dashboard`` serves its UI.

Per run: the experiment is the command's ``experiment_name`` (the training experiment, the sweep, the
ablation or comparison), the name ``logger.run_name`` or the command's, tags ``spread.job_type``, variant,
method, sampler, guidance, seed, git SHA, dataset fingerprint and job id (``spread.*`` keys), the composed
config flattened to params (``a.b.c``). :func:`open_run` starts the run *before* the work (a failed command
leaves a ``FAILED`` run, which its relaunch with the same settings continues: :mod:`spread.tracking.continuation`)
and writes ``<run folder>/mlflow_run.json`` (store, experiment, run id), which is how
a later run finds it: a sampling or evaluation run of a checkpoint records the training run of that
checkpoint (:func:`training_lineage`, tags ``spread.training_run_id`` and ``spread.training_run_folder``).
A run opened while a sweep's, an ablation's or a comparison's parent run is open (in the same store) is nested
under it (:mod:`spread.tracking.parent`, :mod:`spread.tracking.nesting`).

Metrics: every numeric entry of ``metrics.json`` (so each metric with its interval, ``<m>_lo``/``<m>_hi``),
the per-room-type breakdown as ``room/<type>/<entry>``, and ``metrics.json``, ``per_scene.jsonl`` and the
renders as artifacts (:func:`log_evaluation`); while a sampling or evaluation run works, MLflow's monitor logs
its system metrics (``system/*``: CPU, memory, GPU).
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path
from typing import Iterable

from spread.io import read_bytes_checked, read_json_object

#: The file in a run folder that names the run's MLflow run.
RUN_FILE = "mlflow_run.json"
#: Environment variables that carry a scheduler's job id (the first one set wins).
JOB_ID_VARIABLES = ("SLURM_JOB_ID", "PBS_JOBID", "LSB_JOBID", "JOB_ID", "RAY_JOB_ID")
MAX_PARAM_CHARS = 6000  # MLflow's limit on a param value


class StoreError(ValueError):
    """An MLflow store that cannot be used (a path the URI would misread, a corrupt, truncated or locked file);
    the message is one line naming the store."""


#: Characters a SQLite store's path may not hold: SQLAlchemy's URL would read them as a query (``?``), a
#: fragment (``#``) or an escape (``%``), and the store would be elsewhere than printed.
URI_SPECIAL = "?#%"


def resolve_tracking_uri(uri: str | None) -> str:
    """The store's URI: None → ``sqlite:///<cwd>/runs/mlflow.db``; a plain path → a SQLite file; a relative
    ``sqlite:///`` path is made absolute (the commands may run in other folders). Creates the file's folder.
    A SQLite path holding one of :data:`URI_SPECIAL` is refused (:class:`StoreError`)."""
    uri = str(uri) if uri else "runs/mlflow.db"
    if "://" not in uri:
        uri = f"sqlite:///{uri}"
    if uri.startswith("sqlite:///"):
        odd = sorted({c for c in uri[len("sqlite:///"):] if c in URI_SPECIAL})
        if odd:
            raise StoreError(f"MLflow store {uri[len('sqlite:///'):]}: the path holds {' '.join(odd)}, which a "
                             f"store URI reads as a query, fragment or escape (the store would be written "
                             f"elsewhere); use a folder without them (paths.runs_dir=..., logger.tracking_uri=...)")
        path = Path(uri[len("sqlite:///"):]).expanduser()
        path = path if path.is_absolute() else Path.cwd() / path
        path.parent.mkdir(parents=True, exist_ok=True)
        uri = f"sqlite:///{path.resolve()}"
    return uri


def open_store(uri: str):
    """An ``MlflowClient`` of store ``uri`` once the store answers (a new SQLite store gets its tables); a SQLite
    file that is not a regular file, is corrupt, truncated or locked is :class:`StoreError` in one line naming it."""
    from mlflow import MlflowClient

    quiet()
    if uri.startswith("sqlite:///"):
        from spread.io import InputFileError, check_input_file

        path = Path(uri[len("sqlite:///"):])
        if path.exists() or path.is_symlink():
            try:
                check_input_file(path, max_bytes=0)
            except InputFileError as exc:
                raise StoreError(f"MLflow store {exc}") from None
    try:
        client = MlflowClient(tracking_uri=uri)
        client.search_experiments(max_results=1)  # opens the store: creates a new one's tables, reads an old one
    except Exception as exc:
        text = " ".join(str(exc).split()).split(" [SQL:")[0]
        cause = exc.__cause__ or exc.__context__
        detail = f"{type(exc).__name__}: {text[:300]}" if text else type(exc).__name__
        if cause is not None and str(cause) and str(cause)[:80] not in text:
            detail += f" ({type(cause).__name__}: {' '.join(str(cause).split()).split(' [SQL:')[0][:200]})"
        raise StoreError(f"MLflow store {uri}: cannot be opened — {detail}; a corrupt or truncated file must be "
                         f"moved away, a locked one waits for the process that holds it") from None
    return client


def artifact_root(uri: str) -> str | None:
    """Where a new experiment of a SQLite store keeps its artifacts: ``mlartifacts/`` beside the file
    (None for a server, which decides itself)."""
    if uri.startswith("sqlite:///"):
        return str(Path(uri[len("sqlite:///"):]).parent / "mlartifacts")
    return None


def quiet() -> None:
    """MLflow's own console chatter (migrations, 'View run at ...') off."""
    import logging

    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(logging.WARNING)
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")


#: MLflow ≥ 3 opens an experiment on its GenAI (traces) pages unless this tag says it trains models.
EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")


def experiment_id(client, uri: str, name: str) -> str:
    """The id of experiment ``name``, created (artifacts under :func:`artifact_root`) when missing, and tagged
    as a model-training experiment (:data:`EXPERIMENT_KIND`: the UI then opens on its runs)."""
    found = client.get_experiment_by_name(name)
    if found is None:
        root = artifact_root(uri)
        try:
            exp = client.create_experiment(name, artifact_location=None if root is None else
                                           Path(root, safe_name(name)).resolve().as_uri())
        except Exception:  # another process created it meanwhile
            found = client.get_experiment_by_name(name)
            if found is None:
                raise
            exp = found.experiment_id
    else:
        exp = found.experiment_id
    if found is None or found.tags.get(EXPERIMENT_KIND[0]) != EXPERIMENT_KIND[1]:
        client.set_experiment_tag(exp, *EXPERIMENT_KIND)
    return exp


def safe_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name)) or "default"


def flat_params(config: dict, prefix: str = "") -> dict[str, str]:
    """A nested config as ``a.b.c`` → text (lists as JSON), each value cut to MLflow's 6000 characters."""
    out = {}
    for key, value in (config or {}).items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out |= flat_params(value, f"{name}.")
        else:
            text = json.dumps(value) if isinstance(value, (list, tuple)) else str(value)
            out[name] = text[:MAX_PARAM_CHARS]
    return out


def git_sha() -> str | None:
    """The commit of the checkout this code runs from (None outside a git checkout)."""
    try:
        proc = subprocess.run(["git", "rev-parse", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                              text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return proc.stdout.strip() or None if proc.returncode == 0 else None


def job_id() -> str | None:
    return next((os.environ[v] for v in JOB_ID_VARIABLES if os.environ.get(v)), None)


def dataset_fingerprint(root: str | os.PathLike | None) -> str | None:
    """A short content hash of a dataset folder's ``manifest.json`` (what generated it), else of its scene
    file names; None when there is no such folder."""
    import hashlib

    if not root or not Path(root).is_dir():
        return None
    manifest = Path(root) / "manifest.json"
    text = read_bytes_checked(manifest) if manifest.exists() else \
        "\n".join(sorted(str(p.relative_to(root)) for p in Path(root).rglob("*.npz"))).encode()
    return hashlib.sha256(text).hexdigest()[:16]


def common_tags(job_type: str, extra: dict | None = None) -> dict[str, str]:
    """``spread.job_type``, git SHA (also as MLflow's ``mlflow.source.git.commit``), job id, and ``extra``
    (None values left out)."""
    sha = git_sha()
    tags = {"spread.job_type": job_type, "spread.git_sha": sha, "mlflow.source.git.commit": sha,
            "spread.job_id": job_id(), **(extra or {})}
    return {k: str(v) for k, v in tags.items() if v is not None}


def training_lineage(ckpt: str | os.PathLike | None) -> dict[str, str]:
    """Tags naming the training run of checkpoint ``ckpt``: its run folder's :data:`RUN_FILE` (the checkpoint's
    folder or the one above, ``<run>/checkpoints/x.ckpt``), and wandb's id when that folder has one."""
    if not ckpt:
        return {}
    tags = {}
    for folder in (Path(ckpt).parent, Path(ckpt).parent.parent):
        record = folder / RUN_FILE
        if record.exists():
            info = read_json_object(record)
            tags = {"spread.training_run_id": info.get("run_id"), "spread.training_experiment_id":
                    info.get("experiment_id"), "spread.training_run_folder": str(folder.resolve())}
            break
        if (folder / "checkpoints").is_dir() and (folder / ".hydra").is_dir():
            tags["spread.training_run_folder"] = str(folder.resolve())
    from spread.tracking.config import previous_wandb_id

    folder = tags.get("spread.training_run_folder")
    wandb_id = previous_wandb_id(Path(folder)) if folder else None
    if wandb_id:
        tags["spread.training_wandb_id"] = wandb_id
    return {k: str(v) for k, v in tags.items() if v is not None}


def write_run_file(out_dir: str | os.PathLike, uri: str, experiment: str, run_id: str,
                   job_type: str | None = None) -> None:
    """Name run ``run_id`` in ``out_dir``'s :data:`RUN_FILE`: the folder's latest run (``run_id``: whose numbers the
    folder holds now), and under ``jobs`` the latest run of each job type, so a sampling folder evaluated in place
    still names the sampling run that made its scenes (:func:`job_run_id`)."""
    from spread.io import write_json_atomic

    entry = {"tracking_uri": uri, "experiment_id": experiment, "run_id": run_id}
    jobs = read_run_file(out_dir).get("jobs")
    jobs = {k: v for k, v in jobs.items() if isinstance(v, dict)} if isinstance(jobs, dict) else {}
    if job_type:
        jobs[job_type] = entry
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    write_json_atomic(Path(out_dir) / RUN_FILE, {**entry, "jobs": jobs})


def read_run_file(folder: str | os.PathLike) -> dict:
    """``folder``'s :data:`RUN_FILE` as written by :func:`write_run_file`; ``{}`` when there is none or it is
    unreadable (damaged, not an object)."""
    from spread.io import read_json_object

    path = Path(folder) / RUN_FILE
    try:
        return read_json_object(path) if path.is_file() else {}
    except (OSError, ValueError):
        return {}


def job_run_id(folder: str | os.PathLike, job_type: str) -> str | None:
    """The id of the latest ``job_type`` run named in ``folder``'s :data:`RUN_FILE` (:func:`write_run_file`); for a
    record written before ``jobs`` were kept, its one run; None when there is none or the record is unreadable."""
    info = read_run_file(folder)
    jobs = info.get("jobs")
    if isinstance(jobs, dict):
        entry = jobs.get(job_type)
        run_id = entry.get("run_id") if isinstance(entry, dict) else None
    else:
        run_id = info.get("run_id")
    return str(run_id) if isinstance(run_id, str) and run_id else None


class MlflowRun:
    """One open run (through :class:`mlflow.MlflowClient`, no global state): metrics, params, tags,
    artifacts; :meth:`finish` closes it."""

    def __init__(self, client, run_id: str, uri: str):
        self.client, self.run_id, self.uri = client, run_id, uri

    def log_metrics(self, values: dict, step: int = 0) -> None:
        import time

        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, float(v), now, step) for k, v in values.items() if is_number(v)]
        for i in range(0, len(items), 1000):
            self.client.log_batch(self.run_id, metrics=items[i:i + 1000])

    def log_params(self, params: dict) -> None:
        from mlflow.entities import Param

        items = [Param(k, v) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self.client.log_batch(self.run_id, params=items[i:i + 100])

    def set_tags(self, tags: dict) -> None:
        for k, v in tags.items():
            if v is not None:
                self.client.set_tag(self.run_id, k, str(v))

    def log_artifact(self, path: str | os.PathLike, folder: str | None = None) -> None:
        path = Path(path)
        if path.is_dir():
            self.client.log_artifacts(self.run_id, str(path), folder)
        elif path.exists():
            self.client.log_artifact(self.run_id, str(path), folder)

    def finish(self, failed: bool = False) -> None:
        self.client.set_terminated(self.run_id, "FAILED" if failed else "FINISHED")


def is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v


def open_run(logger, job_type: str, out_dir: str | os.PathLike, config: dict, experiment: str,
             name: str | None = None, tags: dict | None = None, continuation=None) -> MlflowRun | None:
    """Start a run (module docstring) in experiment ``experiment``; None when ``logger`` has no ``mlflow``.
    ``continuation``: a :class:`~spread.tracking.continuation.Continuation`; when it names the folder's recorded
    run in this store, that run goes on (status ``RUNNING``, params as first logged, ``spread.launches`` + 1)."""
    from spread.tracking.config import as_logger_config

    logger = as_logger_config(logger)
    if not logger.mlflow:
        return None
    uri = resolve_tracking_uri(logger.tracking_uri)
    client = open_store(uri)
    handle = continued_run(client, uri, continuation.mlflow_run_id(uri), out_dir, job_type) if continuation else None
    if handle is not None:
        return handle
    exp = experiment_id(client, uri, experiment or "Default")
    from spread.tracking.nesting import parent_tags

    all_tags = common_tags(job_type, tags) | {f"tag.{t}": "1" for t in logger.tags} | parent_tags(uri)
    if continuation is not None:  # a run a relaunch may continue counts its launches from the first
        all_tags["spread.launches"] = "1"
    run = client.create_run(exp, tags=all_tags, run_name=logger.run_name or name or Path(out_dir).name)
    handle = MlflowRun(client, run.info.run_id, uri)
    handle.log_params(flat_params(config))
    write_run_file(out_dir, uri, exp, run.info.run_id, job_type)
    return handle


def continued_run(client, uri: str, run_id: str | None, out_dir: str | os.PathLike,
                  job_type: str | None = None) -> MlflowRun | None:
    """Run ``run_id`` of store ``client`` set going again (:func:`open_run`) and named in ``out_dir``'s
    :data:`RUN_FILE`, else None: no id, or the store no longer has it (deleted, or another store at the path)."""
    if not run_id:
        return None
    try:
        run = client.get_run(run_id)
    except Exception:  # noqa: BLE001 - MlflowException (no such run) or a store error: a new run is opened
        return None
    if run.info.lifecycle_stage != "active":
        return None
    try:
        launches = int(run.data.tags.get("spread.launches", "1"))
    except ValueError:
        launches = 1
    client.update_run(run_id, status="RUNNING")
    client.set_tag(run_id, "spread.launches", str(launches + 1))
    from spread.tracking.nesting import parent_tags

    for key, value in parent_tags(uri).items():  # a relaunched sweep's point goes under the relaunch's parent
        client.set_tag(run_id, key, value)
    write_run_file(out_dir, uri, run.info.experiment_id, run_id, job_type)
    return MlflowRun(client, run_id, uri)


def scalar_metrics(metrics: dict) -> dict:
    """The numeric top-level entries of ``metrics.json`` (each metric, ``<m>_lo``/``<m>_hi``, counts; in display
    units, keyed so: ``asd_mm``, :func:`spread.metrics.registry.in_display_units`), the
    per-room-type ones as ``room/<type>/<entry>`` (:func:`spread.tracking.config.room_type_scalars`), and the
    bootstrap settings as ``ci_<key>``."""
    from spread.metrics.registry import in_display_units
    from spread.tracking.config import room_type_scalars

    out = in_display_units({k: v for k, v in metrics.items() if is_number(v)}) | room_type_scalars(metrics)
    boot = metrics.get("bootstrap") or {}
    out |= {f"ci_{k}": boot[k] for k in ("level", "resamples", "seed") if is_number(boot.get(k))}
    return out


def log_evaluation(run: MlflowRun, metrics: dict, out_dir: str | os.PathLike, renders: Iterable = ()) -> None:
    """An evaluation into ``run``: :func:`scalar_metrics`, ``fid_status`` as a tag, and ``metrics.json``,
    ``per_scene.jsonl`` and ``renders`` (files) as artifacts."""
    from spread.runtime.fingerprint import canonical, measured_identity

    run.log_metrics(scalar_metrics(metrics))
    identity = measured_identity(metrics)  # what the numbers measured with (spread.results.load of a store reads it)
    run.set_tags({"spread.fid_status": metrics.get("fid_status"),
                  **({"spread.identity": canonical(identity)} if identity is not None else {})})
    for name in ("metrics.json", "per_scene.jsonl"):
        run.log_artifact(Path(out_dir) / name)
    for path in renders:
        run.log_artifact(path, "renders")


def log_sampling(run: MlflowRun, manifest: dict) -> None:
    """A sampling run's counts, timings and guidance totals (``sampling/*``, ``guidance/*``), its
    ``sampling.json``, renders and 3D figures (artifacts)."""
    numbers = {f"sampling/{k}": v for k, v in manifest.items() if is_number(v)}
    numbers |= {f"guidance/{k}": v for k, v in (manifest.get("guidance_totals") or {}).items() if is_number(v)}
    run.log_metrics(numbers)
    for key in ("renders", "figures"):
        for path in manifest.get(key) or []:
            run.log_artifact(path, key)


def lightning_logger(logger, run_dir: Path, group: str, tags: list[str], config: dict, resuming_here: bool):
    """Lightning's ``MLFlowLogger`` for a training run (experiment ``group``, tags as in :func:`open_run`, the
    config as params); a run resumed from this folder's checkpoint continues the folder's MLflow run. The run
    starts, and :data:`RUN_FILE` is written, on the global rank zero when the fit starts (Lightning logs the
    model's hyperparameters there), whatever launched the processes."""
    from lightning.pytorch.loggers import MLFlowLogger
    from lightning.pytorch.utilities import rank_zero_only

    from spread.tracking.nesting import parent_tags

    quiet()
    uri = resolve_tracking_uri(logger.tracking_uri)
    open_store(uri)  # a store that cannot be opened is one line naming it, before the fit
    record = Path(run_dir) / RUN_FILE
    previous = read_json_object(record).get("run_id") if resuming_here and record.exists() else None
    root = artifact_root(uri)
    data = (config.get("data") or {}) if isinstance(config, dict) else {}
    model = (config.get("model") or {}) if isinstance(config, dict) else {}
    extra = {"spread.variant": model.get("variant") or (model.get("config") or {}).get("variant"),
             "spread.method": model.get("method"), "spread.seed": config.get("seed"),
             "spread.dataset_fingerprint": dataset_fingerprint(data.get("root")),
             "spread.run_folder": str(Path(run_dir).resolve())}

    class RecordedMLFlowLogger(MLFlowLogger):
        """Writes :data:`RUN_FILE`, tags the experiment and logs the config once, on rank zero."""

        recorded = False

        def record(self) -> None:
            if self.recorded:
                return
            self.recorded = True
            run_id = self.run_id  # creates the run
            self.experiment.set_experiment_tag(self.experiment_id, *EXPERIMENT_KIND)
            write_run_file(run_dir, uri, self.experiment_id, run_id, "train")
            if previous is None:
                MlflowRun(self.experiment, run_id, uri).log_params(flat_params(config))

        @rank_zero_only
        def log_hyperparams(self, params) -> None:
            self.record()
            super().log_hyperparams(params)

        @rank_zero_only
        def finalize(self, status: str = "success") -> None:
            self.record()
            super().finalize(status)

    return RecordedMLFlowLogger(
        experiment_name=group, run_name=logger.run_name or f"{group}/{Path(run_dir).name}", tracking_uri=uri,
        tags=common_tags("train", extra) | {f"tag.{t}": "1" for t in [*tags, *logger.tags]} | parent_tags(uri),
        log_model=False,
        run_id=previous, artifact_location=None if root is None else Path(root, safe_name(group)).resolve().as_uri())


class tracked:
    """``with tracked(logger, job_type, out_dir, config, experiment, tags=...) as run:`` — :func:`open_run`
    before the block (``run`` is None without ``mlflow``), ``FINISHED`` after it, ``FAILED`` when it raises.
    ``tags``: a dict or a function returning one (called only when a run opens). ``continuation``: a relaunch
    continues the folder's run (:mod:`spread.tracking.continuation`; the caller writes its record)."""

    def __init__(self, logger, job_type: str, out_dir, config: dict, experiment: str, name: str | None = None,
                 tags=None, continuation=None):
        self.args = (logger, job_type, out_dir, config, experiment, name, tags)
        self.continuation = continuation
        self.run = self.monitor = None

    def __enter__(self) -> MlflowRun | None:
        from spread.tracking.config import as_logger_config

        logger, job_type, out_dir, config, experiment, name, tags = self.args
        if as_logger_config(logger).mlflow:
            self.run = open_run(logger, job_type, out_dir, config, experiment, name,
                                tags() if callable(tags) else tags, self.continuation)
            self.monitor = system_monitor(self.run)
        return self.run

    def __exit__(self, kind, value, traceback) -> None:
        if self.run is not None:
            if self.monitor is not None:
                self.monitor.finish()
            self.run.finish(failed=kind is not None)


#: Seconds between two samples of the system metrics (CPU, memory, GPU) of a sampling or evaluation run.
SYSTEM_METRICS_INTERVAL = 10


def system_monitor(run: MlflowRun):
    """MLflow's system-metrics monitor (``system/cpu_utilization_percentage``, memory, GPU, every
    :data:`SYSTEM_METRICS_INTERVAL` s) on ``run``, started; None where it cannot run (no psutil)."""
    try:
        from mlflow.system_metrics.system_metrics_monitor import SystemMetricsMonitor

        monitor = SystemMetricsMonitor(run.run_id, sampling_interval=SYSTEM_METRICS_INTERVAL,
                                       tracking_uri=run.uri)
        monitor.start()
        return monitor
    except Exception:  # psutil missing, or the monitor refused: the run goes on without system metrics
        return None


def log_table(run: MlflowRun, records: Iterable[dict], label_key: str, files: Iterable = ()) -> None:
    """A results table (an ablation's or a comparison's) into ``run``: each row's numeric entries as
    ``<row label>/<key>`` metrics (in display units, keyed so: ``<row>/asd_mm``), and ``files`` (the table's md/csv/tex/png) as artifacts."""
    from spread.metrics.registry import in_display_units

    values = {}
    for r in records:
        label = safe_name(r.get(label_key))
        numbers = in_display_units({k: v for k, v in r.items() if is_number(v)})
        values |= {f"{label}/{k}": v for k, v in numbers.items()}
    run.log_metrics(values)
    for path in files:
        run.log_artifact(path, "table")
