"""``metrics.json`` values from ``per_scene.jsonl`` records, through the torchmetrics ``merge_state`` path.

Every good record carries its scene's metric states (``record["state"][name]``: the sums one scene adds);
the driver builds fresh aggregates from the protocol and ``merge_state``s each record into them — the same
summation DDP's ``sync`` does across ranks — so the result does not depend on how scenes were split over
workers, nodes or resumed runs. A metric that failed on a scene (the record's ``metric_errors``) leaves that
scene out of its own aggregate only; a record that is damaged (an ``error``, a missing state no ``metric_errors``
explains, a non-finite state) is out of every aggregate (:func:`usable`, :func:`usable_for`). FID and KID: the generated set's features come from the records
(``fid_features``), the reference set's statistics from states merged in by the caller.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from spread.evaluation.protocol import EvalProtocol


def merge_records(records: Iterable[dict], protocol: EvalProtocol) -> dict:
    """Aggregates (name → metric) of the protocol's metrics with every record's per-scene states merged in where
    the record is usable for that metric (:func:`usable_for`). torch loads here, not with the module: a command
    that only composes an :class:`~spread.evaluation.EvaluationConfig` (a refused setting) does not pay for it."""
    import torch

    metrics = protocol.build_metrics()
    for record in records:
        for name, metric in metrics.items():
            if usable_for(record, name, metrics):
                state = record["state"][name]
                metric.merge_state({k: torch.as_tensor(state[k], dtype=getattr(metric, k).dtype)
                                    for k in metric.metric_state})
    return metrics


def usable(record: dict, metrics=None) -> bool:
    """Whether a ``per_scene.jsonl`` record is an evaluated scene that enters the aggregates: no error, and for every
    metric (``metrics``: the names measured, default the record's own) a finite state or a failure the record
    declares (``metric_errors``); a hand-edited or damaged line with a NaN, a string or a missing metric is left
    out of every aggregate, as a failed scene."""
    from spread.evaluation.work import nonfinite_state

    state, declared = record.get("state"), record.get("metric_errors") or {}
    if record.get("error") or not isinstance(state, dict) or not isinstance(declared, dict):
        return False
    names = list(metrics or state)
    if any(n not in state and n not in declared for n in names):
        return False
    measured = {n: state[n] for n in names if n in state and n not in declared}
    if not measured or nonfinite_state(measured) is not None:
        return False
    if isinstance(metrics, dict):  # the metric objects: each state as the metric keeps it
        return all(state_problem(measured[n], metrics[n]) is None for n in measured if n in metrics)
    return True


def state_problem(state: dict, metric) -> str | None:
    """Why a record's ``state`` of ``metric`` cannot be merged into the metric's sums, or None: a state the metric
    keeps is missing, not of the shape it keeps (a list where a number is summed), or not a number its dtype holds —
    an integer state is a count, a whole number ≥ 0 below 2⁵³ (a hand-edited ``-1000`` made every pooled ratio null,
    ``1e300`` overflowed int64). States kept as lists (FID's features) are not records' states."""
    import torch

    for key in metric.metric_state:
        kept = getattr(metric, key)
        if not isinstance(kept, torch.Tensor):
            continue
        if key not in state:
            return f"{key}: missing"
        try:
            values = np.asarray(state[key], dtype=np.float64)
        except (TypeError, ValueError):
            return f"{key}: not a number"
        if values.shape != tuple(kept.shape):
            return f"{key}: of shape {values.shape}, the metric keeps {tuple(kept.shape)}"
        if not np.isfinite(values).all():
            return f"{key}: not finite"
        if not kept.is_floating_point() and not (
                (values == np.round(values)).all() and (values >= 0).all() and (values < 2 ** 53).all()):
            return f"{key}: not a count (a whole number ≥ 0)"
    return None


def usable_for(record: dict, name: str, metrics=None) -> bool:
    """Whether ``record`` enters metric ``name``'s aggregate: :func:`usable`, and ``name`` did not fail on it."""
    return usable(record, metrics) and name in record["state"] and name not in (record.get("metric_errors") or {})


def as_float(value) -> float | None:
    """A 0-d tensor or number as a float, None for NaN (nothing measured) and ±inf (never a result)."""
    x = float(value)
    return None if not np.isfinite(x) else x


def summary_values(records: list[dict], protocol: EvalProtocol) -> dict:
    """Every selected metric's values (its ``compute()``: Stability adds the still shares), the counts of the
    scenes and objects, each metric's own counts (``n_colliding_objects``, ...) and its failures
    (``metric_failures``: name → scenes it failed on) over deduplicated ``records``. A metric whose pooled
    ``compute()`` is not a value of its own (:meth:`~spread.metrics.base.SceneMetric.values`) reports null, with
    why under ``invalid_values``."""
    from spread.metrics.base import MetricOutputError

    metrics = merge_records(records, protocol)
    good = [r for r in records if usable(r, metrics)]
    out: dict = {}
    invalid = {}
    for name, metric in metrics.items():
        try:
            out.update({k: as_float(v) for k, v in metric.values(name).items()})
        except MetricOutputError as exc:
            out[name], invalid[name] = None, str(exc)
    failures = {name: sum(name in (r.get("metric_errors") or {}) for r in good) for name in metrics}
    out.update({"n_scenes": len(records), "n_evaluated": len(good), "n_failed": len(records) - len(good),
                "n_implausible": sum(r.get("error_type") == "ImplausibleSceneError" for r in records),
                "n_refused_inputs": sum(r.get("error_type") == "InputFileError" for r in records),
                "n_objects": int(sum(r["num_objects"] for r in good)),
                "n_metric_failures": sum(failures.values()), "metric_failures": failures})
    if invalid:
        out["invalid_values"] = invalid
    for metric in metrics.values():
        out.update(metric.count_values())
    return out


def fid_values(fid, records: list[dict], status: str, n_reference_files: int, feature_model: str) -> dict:
    """FID and KID fields of ``metrics.json``. ``fid`` is a :class:`~spread.metrics.SceneFID` whose reference
    states are merged in, or None when no extractor is available (then ``status`` says why)."""
    good = [r for r in records if not r.get("error")]
    if fid is None:
        return {"fid": None, "kid": None, "fid_status": status, "fid_feature_model": feature_model,
                "fid_num_generated": len(good), "fid_num_reference": n_reference_files}
    features = [r["fid_features"] for r in good if r.get("fid_features") is not None]
    if features:
        fid.update(features=np.asarray(features, np.float64), real=False)
    out = fid.compute()
    return {"fid": out["fid"], "kid": out["kid"], "fid_status": out["fid_status"],
            "fid_feature_model": out["feature_model"], "fid_num_generated": out["num_generated"],
            "fid_num_reference": out["num_reference"], "kid_subsets": out["kid_subsets"],
            "kid_subset_size": out["kid_subset_size"]}


def per_room_type_values(records: list[dict], protocol: EvalProtocol) -> dict | None:
    """:func:`summary_values` of each room type's records (``record["room_type"]``, from the scene file's
    ``room_type`` array), or None when no record has a room type (FID stays over the whole set)."""
    types = sorted({r["room_type"] for r in records if r.get("room_type")})
    if not types:
        return None
    return {t: summary_values([r for r in records if r.get("room_type") == t], protocol) for t in types}

