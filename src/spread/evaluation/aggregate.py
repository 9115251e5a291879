"""``metrics.json`` values from ``per_scene.jsonl`` records, through the torchmetrics ``merge_state`` path.

Every good record carries its scene's metric states (``record["state"][name]``: the sums one scene adds);
the driver builds fresh aggregates from the protocol and ``merge_state``s each record into them — the same
summation DDP's ``sync`` does across ranks — so the result does not depend on how scenes were split over
workers, nodes or resumed runs. FID and KID: the generated set's features come from the records
(``fid_features``), the reference set's statistics from states merged in by the caller.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np
import torch

from spread.evaluation.protocol import EvalProtocol


def merge_records(records: Iterable[dict], protocol: EvalProtocol) -> dict:
    """Aggregates (name → metric) of the protocol's metrics with every usable record's per-scene states merged in
    (a record without a finite state of every selected metric is left out, as a failure)."""
    metrics = protocol.build_metrics()
    for record in records:
        if not usable(record, metrics):
            continue
        for name, metric in metrics.items():
            state = record["state"][name]
            metric.merge_state({k: torch.as_tensor(state[k], dtype=getattr(metric, k).dtype)
                                for k in metric.metric_state})
    return metrics


def usable(record: dict, metrics=None) -> bool:
    """Whether a ``per_scene.jsonl`` record enters the aggregates: no error and a finite state for every metric
    (``metrics``: the names measured, default the record's own; a hand-edited or damaged line with a NaN, a
    string or a missing metric is left out, as a failure)."""
    from spread.evaluation.work import nonfinite_state

    state = record.get("state")
    return (not record.get("error") and isinstance(state, dict) and set(metrics or state) <= set(state)
            and nonfinite_state(state) is None)


def as_float(value) -> float | None:
    """A 0-d tensor or number as a float, None for NaN (nothing was measured)."""
    x = float(value)
    return None if np.isnan(x) else x


def summary_values(records: list[dict], protocol: EvalProtocol) -> dict:
    """Every selected metric's values (its ``compute()``: Stability adds the still shares), the counts of the
    scenes and objects, and each metric's own counts (``n_colliding_objects``, ...) over deduplicated ``records``."""
    metrics = merge_records(records, protocol)
    good = [r for r in records if usable(r, metrics)]
    out: dict = {}
    for name, metric in metrics.items():
        out.update({k: as_float(v) for k, v in metric.values(name).items()})
    out.update({"n_scenes": len(records), "n_evaluated": len(good), "n_failed": len(records) - len(good),
                "n_implausible": sum(r.get("error_type") == "ImplausibleSceneError" for r in records),
                "n_refused_inputs": sum(r.get("error_type") == "InputFileError" for r in records),
                "n_objects": int(sum(r["num_objects"] for r in good))})
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

