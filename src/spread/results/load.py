"""Any results on disk → one pandas DataFrame: one row per run, every setting of its identity a column, every
metric with its interval.

:func:`load` reads

* a **run folder** (``spread-evaluate`` / ``spread-sample evaluate=true``: ``metrics.json`` + its recorded identity),
  an **ablation** or **comparison** folder, or any folder holding run folders — through
  :func:`spread.reporting.runs.read_runs` (the one reader of run folders and their identities);
* a **sweep folder** (``results.csv`` + ``points/``): each row of ``results.csv`` (its ``point`` folder under
  ``points/``, its ``seed`` with ``seeds=K``, ``status``, ``reused``, the swept values) joined with its point
  folder's record; rows whose point has no evaluation (a training sweep, a trial that failed or was stopped)
  keep the row's own values (``results.csv``'s display units, ``asd_mm``, back in stored units);
* an **MLflow store** (a ``.db`` SQLite file or a URI, :mod:`spread.results.store`).

Columns: ``run``, ``source``, ``kind``, ``identity`` (the digest of every setting), each setting of
:func:`spread.runtime.fingerprint.settings` by name (``guidance.collision``, ``guidance.iterations``, ``sampler``,
``seed``, ``protocol.<key>``, ...), each metric ``<m>`` with ``<m>_lo`` / ``<m>_hi`` in **stored units** (ASD in
metres), ``n_scenes``, and the sweep's own columns. ``df.attrs["settings"]``: the setting columns;
``df.attrs["metrics"]``: the metric columns (:mod:`spread.results.frame`); :func:`~spread.results.frame.display` converts to display units (ASD in mm, headed
``asd_mm``) as the tables show them (:mod:`spread.metrics.registry`).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from spread.results.frame import frame


def load(path) -> pd.DataFrame:
    """The DataFrame of ``path`` (module docstring): a run, sweep, ablation or comparison folder, a folder of
    runs, or an MLflow store (``*.db`` file, ``sqlite:///…``, ``http://…``). ``FileNotFoundError`` naming a
    missing path; :class:`~spread.reporting.runs.RunError` for a folder without runs."""
    text = str(path)
    if "://" in text or text.endswith(".db"):
        from spread.results.store import load_store

        return load_store(text)
    folder = Path(text)
    if not folder.exists():
        raise FileNotFoundError(f"spread.results.load: {folder}: no such file or folder")
    if (folder / "results.csv").exists() and (folder / "points").is_dir():
        return frame(sweep_records(folder))
    from spread.reporting.runs import read_runs

    records, _ = read_runs([str(folder)])
    return frame(records)


def sweep_records(folder: Path) -> list[dict]:
    """One record per ``results.csv`` row of sweep ``folder`` (module docstring)."""
    from spread.reporting.runs import RunError, is_finished_run, read_run_folder
    from spread.reporting.tables import read_csv

    records = []
    for row in read_csv(folder / "results.csv"):
        point = folder / "points" / str(row.get("point")) if row.get("point") else None
        record = {k: v for k, v in row.items() if v is not None and k not in ("settings", "mark")}
        if point is not None and is_finished_run(point):
            try:
                found = read_run_folder(point)
            except RunError:
                found = {}
            record.update({k: v for k, v in found.items() if v is not None or k not in record})
        stored_units(record)
        record.setdefault("run", row.get("point"))
        record.setdefault("source", str(point) if point is not None else str(folder))
        record["kind"] = "sweep"
        records.append(record)
    return records


def stored_units(record: dict) -> None:
    """``results.csv`` holds each metric in its display unit, headed so (``asd_mm``): back to the stored value
    under its own name (``asd`` in metres), unless the point folder's record gave that already."""
    from spread.metrics.registry import METRICS, SCALED_SUFFIXES, display_values, unit_key

    for value in display_values(METRICS.names()):
        shown = unit_key(value.name, value.unit)
        if shown == value.name:
            continue
        for suffix in ("", *SCALED_SUFFIXES):
            cell = record.pop(shown + suffix, None)
            if isinstance(cell, (int, float)) and not isinstance(cell, bool) and value.name + suffix not in record:
                record[value.name + suffix] = cell / float(value.scale)
