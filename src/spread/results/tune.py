"""A sweep's trials as Ray Tune recorded them (``out_dir/tune/<name>/<trial>/``: ``params.json``, ``result.json``
— one JSON line per ``tune.report`` —, ``progress.csv``), and which of them a trial scheduler stopped early.

A training sweep's trial reports every validation (``step``: the trainer's global step, :class:`~spread.
experiments.sweep.TuneReport`) and, once its training finished, a last result naming its ``point`` folder. A
trial whose last result names no point and that did not fail (no ``error.txt``) was **stopped** by the scheduler
(ASHA) at that step. Without Tune's records (a copied sweep folder), ``results.csv`` says the same: a row with
``status`` ok and no ``point``.
"""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

#: Tune's bookkeeping fields of a result (left out of the trial's values).
TUNE_FIELDS = ("timestamp", "checkpoint_dir_name", "done", "trial_id", "date", "time_this_iter_s", "time_total_s",
               "pid", "hostname", "node_ip", "config", "time_since_restore", "iterations_since_restore", "node")


def trial_results(trial: Path) -> list[dict]:
    """The results a trial folder recorded, in order (``result.json``, else ``progress.csv``)."""
    from spread.io import read_text_checked

    path = trial / "result.json"
    if path.exists():
        return [json.loads(line) for line in read_text_checked(path, max_bytes=0).splitlines() if line.strip()]
    if (trial / "progress.csv").exists():
        return pd.read_csv(trial / "progress.csv").to_dict("records")
    return []


def trials(sweep: str | Path) -> pd.DataFrame:
    """One row per trial Ray Tune recorded under ``sweep/tune``: ``trial`` (its folder), ``trial_id``, its
    parameters (a grid point's, unnested), ``reports``, ``step`` (its last reported step, else Tune's
    ``training_iteration``), ``point`` (None until it finished), ``failed``, ``stopped`` and its last values."""
    from spread.io import read_json_object

    rows = []
    for params in sorted(Path(sweep, "tune").glob("*/*/params.json")):
        trial = params.parent
        given = read_json_object(params)
        given = given.get("point", given) if isinstance(given.get("point"), dict) else given
        results = trial_results(trial)
        last = results[-1] if results else {}
        failed = any((trial / f).exists() for f in ("error.txt", "error.pkl"))
        point = last.get("point") if isinstance(last.get("point"), str) and last.get("point") else None
        values = {k: v for k, v in last.items() if k not in TUNE_FIELDS and k not in given}
        rows.append({"trial": trial.name, "trial_id": last.get("trial_id"), **given, **values, "reports": len(results),
                     "step": last.get("step", last.get("training_iteration")), "point": point, "failed": failed,
                     "stopped": bool(results) and point is None and not failed})
    return pd.DataFrame(rows)


def stopped_trials(sweep: str | Path) -> pd.DataFrame:
    """The trials a scheduler stopped early (module docstring), each with ``step``: the last step it reported,
    where it was stopped. From Tune's records, else from ``results.csv``."""
    found = trials(sweep)
    if not found.empty:
        return found[found["stopped"]].reset_index(drop=True)
    csv = Path(sweep) / "results.csv"
    if not csv.exists():
        return pd.DataFrame(columns=["trial", "step", "stopped"])
    from spread.reporting.tables import read_csv

    rows = [r for r in read_csv(csv) if r.get("status") == "ok" and not r.get("point")]
    return pd.DataFrame([{**r, "stopped": True} for r in rows])
