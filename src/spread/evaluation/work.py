"""Worker side of ``spread-evaluate``: one scene file → one ``per_scene.jsonl`` record; a chunk → records.

A record holds every selected metric's values (``compute()`` of a metric that saw this scene only, e.g.
``grecall``, or Stability's ``stability`` and still shares) and diagnostics (the per-scene results' ``to_dict()``
under ``details``), the scene's **torchmetrics states** (``state``: one small dict per metric, what ``metric.update([result])`` leaves in a
fresh metric; the driver sums them with ``merge_state``, as DDP would), seconds per metric, and where it
ran (Ray node id, process id). A scene that cannot be measured (unreadable file, unknown asset, NaN
poses, no objects, ...) gives a record with ``error`` (type and message naming the problem) instead.

Per process, kept across tasks (and across the runs of a sweep whose Ray session stays up): the asset library
of each ``assets`` folder (:mod:`spread.readonce`), the FID extractor, the reference FID states, the metric
objects and the physics world (:func:`spread.physics.get_world`), so a worker pays for loading them once.
"""

from __future__ import annotations

import json
import math
import os
import time
import traceback
from pathlib import Path
from typing import Sequence

import numpy as np

from spread.evaluation.protocol import EvalProtocol, FIDConfig
from spread.runtime.ray import terminated

#: Fault injection for tests: when this environment variable names a file that does not exist yet, the
#: first task to see it creates the file and kills its own worker process (``os._exit``) after its first
#: scene — a worker dying mid-run, to be retried by Ray.
FAULT_MARKER_ENV = "SPREAD_EVAL_FAULT_MARKER"

_EXTRACTORS: dict[tuple, object] = {}
_METRICS: dict[str, dict] = {}


def scene_key(path: str | os.PathLike) -> str:
    """The id a scene file is scheduled, deduplicated and reported under: its file name without ``.npz``
    (DESIGN §4 names scene files ``<scene_id>.npz``), known even when the file cannot be read."""
    return Path(path).stem


def worker_library(assets_dir: str):
    """This process's :class:`~spread.assets.AssetLibrary` of ``assets_dir``, loaded on first use (the one
    table of :func:`spread.readonce.asset_library`, shared with sampling in the same process)."""
    from spread import readonce

    return readonce.asset_library(assets_dir)


def worker_extractor(fid: FIDConfig):
    """This process's FID extractor status (:class:`~spread.metrics.ExtractorStatus`), loaded on first use."""
    key = (fid.enabled, fid.feature_model, fid.weights_path, fid.extractor, fid.device)
    if key not in _EXTRACTORS:
        _EXTRACTORS[key] = load_fid_extractor(fid)
    return _EXTRACTORS[key]


def load_fid_extractor(fid: FIDConfig):
    """The FID extractor from local files (never downloaded), or the ``fid.extractor`` backbone."""
    from spread.metrics import ExtractorStatus, load_extractor

    if not fid.enabled:
        return ExtractorStatus(fid.feature_model, None, 0, "disabled: fid.enabled is false")
    if fid.extractor:
        from spread.registry import resolve

        extractor = resolve(fid.extractor)()
        dim = int(getattr(extractor, "feature_dim", 0)) or \
            int(np.asarray(extractor(np.full((1, 8, 8, 3), 255, np.uint8))).shape[-1])
        return ExtractorStatus(fid.feature_model, extractor, dim, f"ok: extractor {fid.extractor} ('{fid.feature_model}')")
    return load_extractor(fid.feature_model, fid.weights_path, fid.device)


def finite_or_none(value):
    """JSON-safe numbers: NaN and ±inf become None (strict JSON for any reader); recurses into containers."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_none(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_none(v) for v in value]
    return value


def where_am_i() -> dict:
    """Ray node id (None outside Ray) and process id of the code running now."""
    node = None
    try:
        import ray

        if ray.is_initialized():
            node = ray.get_runtime_context().get_node_id()
    except Exception:  # not in a Ray worker
        node = None
    return {"node_id": node, "pid": os.getpid()}


def nonfinite_state(states) -> str | None:
    """The first ``metric.state`` of a record's ``state`` that is missing, not a number or not finite
    (NaN, ±inf, or None after :func:`finite_or_none`), or None when every value is a finite number."""
    for name, state in (states or {}).items():
        if state is not None and not isinstance(state, dict):  # a number or list where a metric's states go
            return name
        for key, value in (state or {}).items():
            values = np.asarray(value if value is not None else np.nan, dtype=object).reshape(-1)
            for v in values:
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                    return f"{name}.{key}"
    return None


def evaluate_scene(path: str | os.PathLike, library, protocol: EvalProtocol, extractor=None,
                   metrics: dict | None = None) -> dict:
    """Every selected metric of one scene file (module docstring); never raises for a bad scene or metric.
    ``metrics``: this process's metric objects (``protocol.build_metrics()``), whose ``evaluate`` measures the scene.

    Metrics are isolated from each other: each gets its own read-only copy of the scene (:func:`read_only_copy`:
    a metric that moves objects raises instead, and can never change what the next one sees), and a metric that
    raises, reports a name that is not its own, a non-number or ±inf, a non-finite state, or details that are not
    JSON fails for this scene alone: ``metric_errors[name]`` says why, its values and state are left out, and the
    other metrics' stand (:func:`measure`). A scene whose every metric failed is a failed scene (``error``)."""
    from spread.metrics import fid_render
    from spread.scene import read_scene

    from spread.io import file_sha256

    record = {"scene_id": scene_key(path), "file": str(path), **where_am_i()}
    try:
        record["input_sha256"] = file_sha256(path)  # what this record was measured on (resume compares it)
    except (OSError, ValueError):  # missing, or not a regular file: read_scene below names the problem
        record["input_sha256"] = None
    seconds: dict[str, float] = {}

    def timed(name, fn, *args, **kwargs):
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        seconds[name] = time.perf_counter() - t0
        return out

    metrics = protocol.build_metrics() if metrics is None else metrics
    values, states, details, failures = {}, {}, {}, {}
    try:
        scene = timed("read", read_scene, path, assets=library)
        for name in metrics:
            outcome = timed(name, measure, metrics, name, scene, library)
            if isinstance(outcome, str):
                failures[name] = outcome
            else:
                values.update(outcome[0])
                states[name], details[name] = outcome[1], outcome[2]
        if not states:
            raise RuntimeError("every metric failed: " + "; ".join(f"{k}: {v}" for k, v in failures.items()))
        features = None
        if extractor is not None:
            image = timed("fid_render", fid_render, scene, library)
            features = timed("fid_features", extractor, image[None])[0]
    except Exception as exc:  # a scene that cannot be measured is reported, and the run goes on
        record.update(error=f"{type(exc).__name__}: {exc}", error_type=type(exc).__name__,
                      traceback=traceback.format_exc(limit=4)[-2000:], seconds=seconds)
        return finite_or_none(record)
    record.update({
        "inner_scene_id": scene.scene_id,
        "room_type": str(scene.extras["room_type"]) if "room_type" in scene.extras else None,
        "num_objects": scene.num_objects,
        **values,
    })
    record.update({
        "details": details,
        "state": states,
        "fid_features": None if features is None else np.asarray(features, np.float64).tolist(),
        "seconds": seconds,
        "error": None,
    })
    if failures:
        record["metric_errors"] = failures
    return finite_or_none(record)


def read_only_copy(scene):
    """A copy of ``scene`` whose arrays cannot be written (a metric measures it; it never edits what the next
    metric or the FID render sees)."""
    copy = scene.with_poses(scene.translation, scene.rotation)
    for array in (copy.asset_id, copy.category, copy.translation, copy.rotation, copy.spatial, copy.physical,
                  copy.room, *copy.extras.values()):
        if isinstance(array, np.ndarray):
            array.flags.writeable = False
    return copy


def measure(metrics: dict, name: str, scene, library) -> tuple[dict, dict, dict] | str:
    """(values, state, details) of metric ``name`` on ``scene`` (its own read-only copy), or why it failed, in
    one line naming the metric (:func:`evaluate_scene`)."""
    try:
        result = metrics[name].evaluate(read_only_copy(scene), library)
        one = protocol_metric(metrics, name)  # a fresh metric that sees this scene only
        one.update([result])
        values = one.values(name)  # only its own names, numbers, never ±inf (SceneMetric.values)
        state = {k: v.tolist() for k, v in one.metric_state.items()}
        bad = nonfinite_state({name: state})
        if bad:
            raise FloatingPointError(f"metric state {bad} is not finite")
        detail = finite_or_none(result.to_dict())
        try:
            json.dumps(detail, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise TypeError(f"its to_dict() is not JSON ({exc})") from None
    except (Exception, SystemExit) as exc:  # this metric fails for this scene; the others stand
        if terminated(exc):  # SIGTERM while it measured: the command stops, not this metric
            raise
        return f"{type(exc).__name__}: {str(exc)[:500] or '(no message)'}"
    return values, state, detail


def protocol_metric(metrics: dict, name: str):
    """A fresh copy of ``metrics[name]`` with empty states (same settings)."""
    metric = metrics[name].clone()
    metric.reset()
    return metric


def worker_metrics(protocol: EvalProtocol) -> dict:
    """This process's metric objects of ``protocol`` (built once per protocol and reused across tasks)."""
    import json

    key = json.dumps(protocol.fingerprint(), sort_keys=True, default=str)
    if key not in _METRICS:
        _METRICS.clear()
        _METRICS[key] = protocol.build_metrics()
    return _METRICS[key]


def maybe_inject_fault(done_in_chunk: int) -> None:
    """Kill this worker process once per marker file (see :data:`FAULT_MARKER_ENV`); tests only."""
    marker = os.environ.get(FAULT_MARKER_ENV)
    if not marker or done_in_chunk < 1:
        return
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return
    os.write(fd, f"killed pid {os.getpid()}\n".encode())
    os.close(fd)
    os._exit(1)


def evaluate_chunk(paths: Sequence[str], assets_dir: str, protocol: EvalProtocol, fid: FIDConfig) -> list[dict]:
    """Evaluate scene files in this process, in order; one record each (the body of a Ray task)."""
    library = worker_library(assets_dir)
    extractor = worker_extractor(fid).extractor
    metrics = worker_metrics(protocol)
    records = []
    for path in paths:
        records.append(evaluate_scene(path, library, protocol, extractor, metrics))
        maybe_inject_fault(len(records))
    return records


def failure_record(path: str, exc: BaseException) -> dict:
    """The record of a scene whose single-scene task failed after its retries (:mod:`~spread.evaluation.fanout`)."""
    return {"scene_id": scene_key(path), "file": str(path), "node_id": None, "pid": None,
            "error": f"worker failed while evaluating this scene ({type(exc).__name__}: {str(exc)[:500]})",
            "error_type": type(exc).__name__}


def reference_fid_state(paths: Sequence[str], assets_dir: str, fid: FIDConfig, seed: int) -> dict:
    """FID states of reference scenes (the real set): ``{"state": SceneFID.metric_state, "failed": [...]}``.

    Scenes that cannot be rendered are listed in ``failed`` (id, error) and left out of the statistics.
    Kept per process while the files are unchanged (:mod:`spread.readonce`): a second evaluation
    against the same reference in a warm worker (the next sweep trial) renders nothing again.
    """
    from spread import readonce

    try:
        key = (tuple(readonce.file_key(p) for p in paths), readonce.file_key(Path(assets_dir) / "index.json"),
               json.dumps(fid.fingerprint(), sort_keys=True), int(seed))
    except OSError:  # a file gone: computed (and its failure listed) without keeping it
        return _reference_fid_state(paths, assets_dir, fid, seed)
    return readonce.memo("fid_reference", key, lambda: _reference_fid_state(paths, assets_dir, fid, seed))


def _reference_fid_state(paths: Sequence[str], assets_dir: str, fid: FIDConfig, seed: int) -> dict:
    from spread.metrics import SceneFID, fid_render
    from spread.scene import read_scene

    library = worker_library(assets_dir)
    loaded = worker_extractor(fid)
    if loaded.extractor is None:
        raise RuntimeError(f"reference FID features need an extractor: {loaded.status}")
    metric = SceneFID(fid.feature_model, extractor=loaded.extractor, feature_dim=loaded.feature_dim or None,
                      kid_seed=seed)
    images, failed = [], []
    for path in paths:
        try:
            images.append(fid_render(read_scene(path, assets=library), library))
        except Exception as exc:
            failed.append({"scene_id": scene_key(path), "error": f"{type(exc).__name__}: {exc}"})
    if images:
        metric.update(images=np.stack(images), real=True)
    state = {k: [t.cpu() for t in v] if isinstance(v, list) else v.cpu() for k, v in metric.metric_state.items()}
    return {"state": state, "failed": failed}
