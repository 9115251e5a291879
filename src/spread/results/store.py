"""An MLflow store (``logger=mlflow``'s; :mod:`spread.tracking.mlflow_store`) → the frame of
:func:`spread.results.load`: one row per run that logged an evaluation (a registered metric), its identity's
settings as columns.

A run's settings come from its run folder when that folder is still there (``spread.run_folder`` tag, else the
``out_dir`` param: :func:`spread.reporting.runs.read_run_folder`, the same record a folder gives); else from its
params (the composed config, flattened ``a.b.c``) through :func:`spread.runtime.fingerprint.config_identity`. The
store's own fields: ``run_id``, ``experiment``, ``run_name``, ``status``, ``parent_run_id`` (a sweep's, an
ablation's or a comparison's parent run, :mod:`spread.tracking.parent`), ``reused`` and ``made_by_run_id`` (a
point a relaunch re-used). Parent runs themselves (``spread.kind`` tag) are not rows.
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd


def parsed(text: str):
    """A param's text back to its value (JSON where it parses: numbers, lists, null, booleans)."""
    try:
        return json.loads(text)
    except (TypeError, ValueError):
        return {"True": True, "False": False, "None": None}.get(text, text)


def made_the_folder(run_id: str, folder, tagged: str | None = None) -> bool:
    """Whether the run folder's numbers are this MLflow run's: its ``mlflow_run.json`` names this run (a folder
    evaluated again since holds a later run's numbers and settings; this run's own logged values are its record),
    or names none (a folder written before that record); and what its ``metrics.json`` measured with is what the run
    recorded (``tagged``: its ``spread.identity`` tag): a redo without MLflow (``logger=none``, another seed or
    protocol) leaves ``mlflow_run.json`` naming the run whose numbers it replaced."""
    from spread.io import read_json_object
    from spread.runtime.fingerprint import identity_changes, measured_identity, tracked_identity
    from spread.tracking.mlflow_store import RUN_FILE

    path = Path(str(folder)) / RUN_FILE
    try:
        named = read_json_object(path).get("run_id") if path.is_file() else None
        measured = tracked_identity(tagged) if tagged else None
        now = measured_identity(read_json_object(Path(str(folder)) / "metrics.json")) if measured else None
    except (OSError, ValueError):
        return False
    if named is not None and named != run_id:
        return False
    return measured is None or now is None or not identity_changes(measured, now)


def run_record(run, experiments: dict) -> dict | None:
    """The record of one MLflow run (module docstring); None for a parent run or a run without a metric."""
    from spread.reporting.runs import RunError, identity_fields, is_finished_run, read_run_folder, record_metrics
    from spread.metrics.registry import in_stored_units
    from spread.runtime.fingerprint import config_identity, tracked_identity, upgraded

    tags, metrics, params = run.data.tags, in_stored_units(run.data.metrics), run.data.params
    if tags.get("spread.kind") or not any(m in metrics for m in record_metrics()):
        return None
    record = None
    folder = tags.get("spread.run_folder") or params.get("out_dir")
    reused = tags.get("spread.reused") == "true"
    made_by = tags.get("spread.made_by_run_id") if reused else run.info.run_id  # a re-used point: the point's run
    if folder and made_by and is_finished_run(folder) and made_the_folder(made_by, folder, tags.get("spread.identity")):
        try:
            record = read_run_folder(folder)
        except RunError:
            record = None
    if record is None:
        measured = tracked_identity(tags.get("spread.identity"))  # what its numbers measured with (metrics.json's)
        try:
            identity = upgraded(measured) if measured is not None else \
                config_identity({k: parsed(v) for k, v in params.items()})
        except Exception:  # a config this version cannot type (an older run): its params as they are
            identity = {}
        record = {"run": run.info.run_name, "source": folder, **identity_fields(identity)}
        record.update({k: v for k, v in metrics.items() if "/" not in k})
    record.update(kind="mlflow", run_id=run.info.run_id, experiment=experiments.get(run.info.experiment_id),
                  run_name=run.info.run_name, status=run.info.status, parent_run_id=tags.get("mlflow.parentRunId"),
                  reused=reused, made_by_run_id=tags.get("spread.made_by_run_id"))
    return record


def load_store(uri: str) -> pd.DataFrame:
    """The frame of the store at ``uri`` (a ``.db`` path or a URI; module docstring)."""
    from spread.results.frame import frame
    from spread.tracking.mlflow_store import open_store, resolve_tracking_uri

    if "://" not in uri and not Path(uri).exists():
        raise FileNotFoundError(f"spread.results.load: {uri}: no such MLflow store")
    client = open_store(resolve_tracking_uri(uri))
    experiments = {e.experiment_id: e.name for e in client.search_experiments()}
    runs, token = [], None
    while True:
        page = client.search_runs(list(experiments), max_results=1000, page_token=token)
        runs += list(page)
        token = page.token
        if not token:
            break
    records = [r for r in (run_record(run, experiments) for run in runs) if r is not None]
    return frame(records)
