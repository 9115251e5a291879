"""Multi-run commands on the dashboard: one MLflow **parent run** per sweep, ablation or comparison, with every
trial's or stage's run nested under it (MLflow's tag ``mlflow.parentRunId``), and the stores the children
write to fixed before any of them starts.

* :func:`absolute_tracking_overrides` — in the driver, before any trial or stage, with ``logger=mlflow``:
  ``paths.runs_dir`` and ``logger.tracking_uri`` made absolute, so a trial that runs in another working directory (Ray Tune
  runs each trial in its own temporary folder) writes to the store the dashboard reads (``spread-dashboard``:
  ``<paths.runs_dir>/mlflow.db``).
* :class:`ParentRun` (``with parent_run(logger, kind, name, out_dir, experiment) as parent:``) — opens the
  parent run (tags ``spread.kind`` = ``sweep`` | ``ablation`` | ``comparison``, ``spread.name``,
  ``spread.out_dir``) and, while the block runs, names it in the environment variable :data:`PARENT_ENV`
  (JSON: run id, store, experiment). Every run :func:`spread.tracking.mlflow_store.open_run` or a training
  run's MLflow logger opens meanwhile *in the same store* gets :func:`parent_tags` — in this process, in a
  subprocess (a launched training stage) and in a local Ray session's workers, which inherit the driver's
  environment. :func:`nested_trial` carries it to a Ray Tune trial explicitly (a remote cluster's workers
  do not inherit it). :func:`nest_under` makes an already open run (the ablation's table run) the parent.
* :meth:`ParentRun.log_reused` — a point a relaunch re-used (no trial ran, or the trial found it finished) gets
  a child run of its own tagged ``spread.reused=true`` with its metrics, and ``spread.made_by_run_id``: the run
  that made it (the point folder's ``mlflow_run.json``, else the store's run whose ``out_dir`` param is the
  folder), so a finished sweep shows every point.

wandb: a sweep's trials, an ablation's or a comparison's stages already share one group (``experiment_name``:
the sweep's ``name``, the study's ``<kind>_<name>``); nothing more is needed there.
"""

from __future__ import annotations

import contextlib
import functools
import os
from pathlib import Path
from typing import Iterator

from spread.tracking.nesting import PARENT_ENV, environment, parent_tags  # noqa: F401

#: Row fields that are bookkeeping, not results (left out of a re-used point's metrics).
NOT_METRICS = ("trial_seconds", "trial_pid", "startup_seconds", "best", "reused", "seed")


def absolute_tracking_overrides(cfg) -> list[str]:
    """Overrides that pin a command's stores to absolute paths (module docstring), from its composed config
    ``cfg`` (a DictConfig or a dict, resolved in this process's working directory), when its logger writes to
    MLflow: ``paths.runs_dir=<abs>`` when relative and ``logger.tracking_uri=<abs URI>``. [] when nothing moves —
    without MLflow nothing a trial writes depends on them (its out_dir is given), and a training point's
    identity (its whole config) stays as it was."""
    from omegaconf import OmegaConf

    from spread.tracking.config import as_logger_config
    from spread.tracking.mlflow_store import resolve_tracking_uri

    plain = OmegaConf.to_container(cfg, resolve=True) if OmegaConf.is_config(cfg) else dict(cfg)
    logger = plain.get("logger")
    if not logger or not as_logger_config(logger).mlflow:
        return []
    out = []
    runs_dir = (plain.get("paths") or {}).get("runs_dir")
    if runs_dir and not Path(str(runs_dir)).is_absolute():
        out.append(f"paths.runs_dir={quoted(str(Path(str(runs_dir)).resolve()))}")
    given = as_logger_config(logger).tracking_uri
    uri = resolve_tracking_uri(given)
    if uri != given:
        out.append(f"logger.tracking_uri={quoted(uri)}")
    return out


def quoted(value: str) -> str:
    """``value`` as a Hydra override value: quoted when it holds characters Hydra's grammar reads otherwise."""
    plain = all(c.isalnum() or c in "/._-:" for c in value)
    return value if plain else "'" + value.replace("\\", "\\\\").replace("'", "\\'") + "'"


def nested_trial(trial):
    """``trial`` (a Ray Tune function trainable) running under the parent run open *now*, in whatever process
    Tune runs it (the parent travels in the closure); ``trial`` itself when no parent is open."""
    parent = os.environ.get(PARENT_ENV)
    if not parent:
        return trial

    @functools.wraps(trial)
    def nested(config, **kwargs):
        with environment(parent):
            return trial(config, **kwargs)

    return nested


class ParentRun:
    """An open parent run (module docstring); ``run`` is its :class:`~spread.tracking.mlflow_store.MlflowRun`
    (None: the logger has no MLflow, and every method does nothing)."""

    def __init__(self, run, kind: str = "", experiment: str | None = None):
        self.run, self.kind, self.experiment = run, kind, experiment

    @property
    def info(self) -> dict | None:
        if self.run is None:
            return None
        return {"run_id": self.run.run_id, "tracking_uri": self.run.uri, "experiment_id": self.experiment,
                "kind": self.kind}

    def log_files(self, paths) -> None:
        """``paths`` (a results table, say) as the parent run's artifacts."""
        if self.run is not None:
            for path in paths:
                self.run.log_artifact(path)

    def log_reused(self, rows: list[dict], points: str | Path) -> list[str]:
        """A child run per row with ``reused`` true (its point folder ``points/<row["point"]>``): tags
        ``spread.reused=true``, ``spread.point``, ``spread.made_by_run_id``; its metrics (the folder's
        ``metrics.json`` when it is an evaluation's, else the row's numbers). Returns the child runs' ids."""
        if self.run is None:
            return []
        ids = []
        for row in rows:
            if str(row.get("reused")).lower() != "true" or not row.get("point"):
                continue
            ids.append(self.reused_child(row, Path(points) / str(row["point"])))
        return ids

    def reused_child(self, row: dict, folder: Path) -> str:
        from spread.tracking.mlflow_store import MlflowRun, common_tags, is_number, scalar_metrics

        client = self.run.client
        made_by = original_run(client, self.run.uri, folder)
        tags = common_tags("sample" if (folder / "sampling.json").exists() else "train", {
            "mlflow.parentRunId": self.run.run_id, "spread.parent_kind": self.kind, "spread.reused": "true",
            "spread.point": folder.name, "spread.run_folder": str(folder.resolve()),
            "spread.fingerprint": row.get("fingerprint"), "spread.made_by_run_id": made_by})
        child = client.create_run(self.experiment, tags=tags, run_name=f"{folder.name} (re-used)")
        handle = MlflowRun(client, child.info.run_id, self.run.uri)
        metrics = read_evaluation(folder)
        values = scalar_metrics(metrics) if metrics else {}
        from spread.metrics.registry import in_display_units

        row_values = in_display_units({k: v for k, v in row.items() if is_number(v) and k not in NOT_METRICS})
        values |= {k: v for k, v in row_values.items() if k not in values}  # one unit a value, as scalar_metrics
        handle.log_metrics({safe_key(k): v for k, v in values.items()})
        handle.finish()
        return child.info.run_id


def safe_key(key: str) -> str:
    """An MLflow metric name (letters, digits, ``_-./ ``; a swept key's ``+`` dropped)."""
    return "".join(c if c.isalnum() or c in "_-./ " else "_" for c in str(key).lstrip("+~"))


def read_evaluation(folder: Path) -> dict:
    """The folder's ``metrics.json`` when it is an evaluation's (a sampling point), else {}."""
    from spread.io import read_json_object

    path = folder / "metrics.json"
    if not path.exists():
        return {}
    try:
        metrics = read_json_object(path)
    except (OSError, ValueError):
        return {}
    return metrics if "n_evaluated" in metrics or "n_scenes" in metrics else {}


def original_run(client, uri: str, folder: Path) -> str | None:
    """The id of the run that made point ``folder``: its ``mlflow_run.json`` (when in store ``uri``), else the
    store's newest run whose ``out_dir`` param is the folder; None when the store has none."""
    from spread.io import read_json_object
    from spread.tracking.mlflow_store import RUN_FILE

    record = folder / RUN_FILE
    if record.exists():
        try:
            info = read_json_object(record)
        except (OSError, ValueError):
            info = {}
        if info.get("run_id") and info.get("tracking_uri") == uri:
            return str(info["run_id"])
    experiments = [e.experiment_id for e in client.search_experiments()]
    for path in dict.fromkeys([str(folder), str(folder.resolve())]):
        found = client.search_runs(experiments, filter_string=f"params.out_dir = '{path}'",
                                   order_by=["attributes.start_time DESC"], max_results=5)
        found = [r for r in found if r.data.tags.get("spread.reused") != "true"]
        if found:
            return found[0].info.run_id
    return None


@contextlib.contextmanager
def parent_run(logger, kind: str, name: str, out_dir: str | Path, experiment: str,
               config: dict | None = None) -> Iterator[ParentRun]:
    """Open the parent run of a ``kind`` (``sweep``, ``ablation``, ``comparison``) called ``name`` writing into
    ``out_dir``, in MLflow experiment ``experiment`` (where its children go), for the block (module docstring);
    ``FAILED`` when the block raises. A logger without MLflow: a :class:`ParentRun` that does nothing."""
    from spread.tracking.config import as_logger_config
    from spread.tracking.mlflow_store import MlflowRun, common_tags, experiment_id, flat_params, open_store, \
        resolve_tracking_uri

    logger = as_logger_config(logger)
    if not logger.mlflow:
        yield ParentRun(None, kind)
        return
    uri = resolve_tracking_uri(logger.tracking_uri)
    client = open_store(uri)
    exp = experiment_id(client, uri, experiment or "Default")
    tags = common_tags(kind, {"spread.kind": kind, "spread.name": name, "spread.out_dir": str(Path(out_dir).resolve()),
                              **{f"tag.{t}": "1" for t in logger.tags}})
    created = client.create_run(exp, tags=tags, run_name=f"{kind}/{name}")
    handle = MlflowRun(client, created.info.run_id, uri)
    if config:
        handle.log_params(flat_params(config))
    parent = ParentRun(handle, kind, exp)
    failed = True
    try:
        with environment(parent.info):
            yield parent
        failed = False
    finally:
        handle.finish(failed=failed)


@contextlib.contextmanager
def nest_under(run, kind: str, name: str, out_dir: str | Path) -> Iterator[ParentRun]:
    """Make ``run`` (an open :class:`~spread.tracking.mlflow_store.MlflowRun`, or None) the parent of the runs
    opened in the block: tagged as :func:`parent_run` tags its run; it is not closed here."""
    if run is None:
        yield ParentRun(None, kind)
        return
    run.set_tags({"spread.kind": kind, "spread.name": name, "spread.out_dir": str(Path(out_dir).resolve())})
    experiment = run.client.get_run(run.run_id).info.experiment_id
    parent = ParentRun(run, kind, experiment)
    with environment(parent.info):
        yield parent
