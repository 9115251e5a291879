"""Confidence intervals for the rows of the platform's tables (ablation, report, compare).

A row's interval fields are ``<metric>_lo`` / ``<metric>_hi`` (:mod:`spread.evaluation.bootstrap`): taken from
``metrics.json`` when the evaluation wrote them, else computed from the ``per_scene.jsonl`` beside it (a run
evaluated before intervals existed) with the protocol's seed, else none. :func:`ci_columns` flattens the
bootstrap's settings into plain row fields, so CSV files record the seed and the number of resamples.

Any table built with :func:`spread.reporting.tables.write_tables` prints ``value ± half-width`` for a
column ``key`` as soon as its rows hold ``key_lo`` / ``key_hi``: a new table gets intervals by
``row.update(ci_columns(row_intervals(metrics, eval_folder)))`` per row and ``note=table_note(rows)``; columns
of a subset of the scenes (e.g. Col_mesh per room type, ``col_mesh/<room>``) by :func:`grouped_intervals`.
"""

from __future__ import annotations

from pathlib import Path

from typing import Callable, Iterable

from spread.evaluation.bootstrap import (
    FEW, bootstrap_intervals, few_measured, interval_note, pooled, record_metrics, scene_sums,
)
from spread.reporting.tables import CI_SETTINGS


def interval_keys(intervals: dict) -> list[str]:
    """The ``<value>_lo`` / ``<value>_hi`` fields of a bootstrap result or ``metrics.json`` (whichever registered
    metrics the run selected), in order."""
    values = [k[:-3] for k in intervals if k.endswith("_lo") and f"{k[:-3]}_hi" in intervals]
    return [f"{m}_{b}" for m in values for b in ("lo", "hi")]


def row_intervals(metrics: dict, folder: str | Path | None) -> dict:
    """``{"<metric>_lo": .., "<metric>_hi": .., "bootstrap": {...}}`` for one evaluated run; {} when neither
    ``metrics`` nor ``folder/per_scene.jsonl`` gives them."""
    if metrics.get("bootstrap"):
        return {**{k: metrics.get(k) for k in interval_keys(metrics)}, "bootstrap": metrics["bootstrap"]}
    if metrics.get("bootstrap_resamples") == 0:  # the evaluation was asked for none
        return {}
    records = folder_records(folder)
    if records is None:
        return {}
    return bootstrap_intervals(records, seed=protocol_seed(metrics, folder))


def protocol_seed(metrics: dict, folder=None) -> int:
    """The evaluation's seed (``metrics.json``'s ``protocol.seed``; 0 when it has none); ``ValueError`` naming the
    file and key when it is not a whole number."""
    protocol = metrics.get("protocol") if isinstance(metrics.get("protocol"), dict) else {}
    seed = protocol.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        where = Path(folder) / "metrics.json" if folder is not None else "metrics.json"
        raise ValueError(f"{where}: protocol.seed={seed!r}: not a whole number")
    return seed


def folder_records(folder: str | Path | None) -> list[dict] | None:
    """The deduplicated ``per_scene.jsonl`` lines of an evaluation folder sorted by scene id, None without it: those
    of the scenes its ``metrics.json`` counted (``evaluated_scenes``; lines of other scenes, left by an evaluation of
    another scene folder into it, are not its numbers), all of them for a ``metrics.json`` written before that
    record."""
    path = Path(folder) / "per_scene.jsonl" if folder is not None else None
    if path is None or not path.exists():
        return None
    from spread.evaluation.resume import dedupe
    from spread.io import read_json_object, read_jsonl

    try:
        counted = read_json_object(Path(folder) / "metrics.json").get("evaluated_scenes")
    except (OSError, ValueError):
        counted = None
    keep = set(map(str, counted)) if isinstance(counted, list) else None
    return [r for k, r in sorted(dedupe(read_jsonl(path)).items()) if keep is None or str(k) in keep]


def grouped_intervals(records: Iterable[dict], group_of: Callable[[str], str | None], metrics: Iterable[str],
                      seed: int = 0) -> dict:
    """``{"<metric>/<group>": value, "<metric>/<group>_lo": .., "<metric>/<group>_hi": ..}`` for the scenes of
    each group (``group_of(scene_id)``; None leaves a scene out): the pooled value and its bootstrap over that
    group's scenes alone, every group with the same ``seed``. For table columns over a subset of the scenes."""
    groups: dict[str, list[dict]] = {}
    for r in records:
        group = None if r.get("error") else group_of(r["scene_id"])
        if group is not None:
            groups.setdefault(group, []).append(r)
    out = {}
    for group, rows in sorted(groups.items()):
        boot = bootstrap_intervals(rows, seed=seed)
        sums = scene_sums(rows, record_metrics(rows))
        for metric in metrics:
            if metric not in sums:
                raise ValueError(f"grouped_intervals: unknown metric '{metric}' (choose from {list(sums)})")
            value = pooled(*sums[metric])
            out[f"{metric}/{group}"] = None if value != value else value
            out[f"{metric}/{group}_lo"], out[f"{metric}/{group}_hi"] = boot[f"{metric}_lo"], boot[f"{metric}_hi"]
    return out


def ci_columns(intervals: dict) -> dict:
    """The interval fields of a row plus ``ci_level``, ``ci_resamples``, ``ci_seed`` and ``ci_few`` (the metrics
    too few scenes measured, :func:`~spread.evaluation.bootstrap.few_measured`; None without intervals)."""
    meta = intervals.get("bootstrap") or {}
    return {**{k: intervals.get(k) for k in interval_keys(intervals)},
            **{k: meta.get(k.removeprefix("ci_")) for k in CI_SETTINGS if k != "ci_few"},
            "ci_few": (few_measured(meta) or None) if meta else None}


def table_note(records) -> str:
    """What ± means in a table of ``records`` (rows with ``ci_*`` fields); names every seed used."""
    metas = [r for r in records if r.get("ci_resamples")]
    if not metas:
        return ""
    seeds = sorted({r["ci_seed"] for r in metas})
    first = metas[0]
    note = interval_note({"level": first["ci_level"], "method": "percentile", "resamples": first["ci_resamples"],
                          "seed": seeds[0]})
    if len(seeds) > 1 or len({(r["ci_level"], r["ci_resamples"]) for r in metas}) > 1:
        note += f" (rows differ: seeds {seeds}; see the CSV's ci_* columns)"
    few = [f"{r.get('method') or r.get('run') or i}: {r['ci_few']}" for i, r in enumerate(metas) if r.get("ci_few")]
    if few:
        note += f" Fewer than {FEW} scenes measured " + "; ".join(few) + ": too few for a trustworthy interval."
    return note
