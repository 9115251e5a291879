"""Worker side of ``spread-evaluate``: one scene file → one ``per_scene.jsonl`` record; a chunk → records.

A record holds every metric's value and diagnostics (the per-scene results' ``to_dict()``), the scene's
**torchmetrics states** (``state``: one small dict per metric, what ``metric.update([result])`` leaves in a
fresh metric; the driver sums them with ``merge_state``, as DDP would), seconds per metric, and where it
ran (Ray node id, process id). A scene that cannot be measured (unreadable file, unknown asset, NaN
poses, no objects, ...) gives a record with ``error`` (type and message naming the problem) instead.

Per process, kept across tasks: the asset library of each ``assets`` folder, the FID extractor, and the
pybullet world (:func:`spread.physics.get_world`), so a worker pays for loading them once.
"""

from __future__ import annotations

import math
import os
import time
import traceback
from pathlib import Path
from typing import Sequence

import numpy as np

from spread.evaluation.protocol import EvalProtocol, FIDConfig

#: Fault injection for tests: when this environment variable names a file that does not exist yet, the
#: first task to see it creates the file and kills its own worker process (``os._exit``) after its first
#: scene — a worker dying mid-run, to be retried by Ray.
FAULT_MARKER_ENV = "SPREAD_EVAL_FAULT_MARKER"

_LIBRARIES: dict[str, object] = {}
_EXTRACTORS: dict[tuple, object] = {}


def scene_key(path: str | os.PathLike) -> str:
    """The id a scene file is scheduled, deduplicated and reported under: its file name without ``.npz``
    (DESIGN §4 names scene files ``<scene_id>.npz``), known even when the file cannot be read."""
    return Path(path).stem


def worker_library(assets_dir: str):
    """This process's :class:`~spread.assets.AssetLibrary` of ``assets_dir``, loaded on first use."""
    from spread.assets import AssetLibrary

    key = str(Path(assets_dir).resolve())
    if key not in _LIBRARIES:
        _LIBRARIES[key] = AssetLibrary.load(key)
    return _LIBRARIES[key]


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
        import importlib

        module, _, attr = fid.extractor.partition(":")
        extractor = getattr(importlib.import_module(module), attr)()
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


def scene_states(results: dict, protocol: EvalProtocol) -> dict:
    """Per-metric torchmetrics states ({name: {state: number}}) of one scene's results."""
    states = {}
    for name, metric in protocol.metrics().items():
        metric.update([results[name]])
        states[name] = {k: v.tolist() for k, v in metric.metric_state.items()}
    return states


def nonfinite_state(states) -> str | None:
    """The first ``metric.state`` of a record's ``state`` that is missing, not a number or not finite
    (NaN, ±inf, or None after :func:`finite_or_none`), or None when every value is a finite number."""
    for name, state in (states or {}).items():
        for key, value in (state or {}).items():
            values = np.asarray(value if value is not None else np.nan, dtype=object).reshape(-1)
            for v in values:
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                    return f"{name}.{key}"
    return None


def evaluate_scene(path: str | os.PathLike, library, protocol: EvalProtocol, extractor=None) -> dict:
    """Every metric of one scene file (module docstring); never raises for a bad scene."""
    from spread.metrics import (
        fid_render, scene_collisions, scene_graph_recall, scene_seed, scene_stability, scene_support_distance,
    )
    from spread.physics import get_world
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

    try:
        scene = timed("read", read_scene, path, assets=library)
        results = {
            "col_mesh": timed("col_mesh", scene_collisions, scene, library, protocol.collision_threshold),
            "grecall": timed("grecall", scene_graph_recall, scene, library),
            "asd": timed("asd", scene_support_distance, scene, library),
            "stability": timed("stability", scene_stability, scene, library, protocol.stability_runs,
                               protocol.stability_steps, protocol.stability_dt, protocol.stability_jitter,
                               seed=scene_seed(scene.scene_id, protocol.seed),
                               world=get_world(protocol.physics_params())),
        }
        features = None
        if extractor is not None:
            image = timed("fid_render", fid_render, scene, library)
            features = timed("fid_features", extractor, image[None])[0]
        states = scene_states(results, protocol)
        bad = nonfinite_state(states)
        if bad:
            raise FloatingPointError(f"{path}: metric state {bad} is not finite; the scene is left out of every "
                                     f"aggregate")
    except Exception as exc:  # a scene that cannot be measured is reported, and the run goes on
        record.update(error=f"{type(exc).__name__}: {exc}", error_type=type(exc).__name__,
                      traceback=traceback.format_exc(limit=4)[-2000:], seconds=seconds)
        return record
    stability = results["stability"]
    record.update({
        "inner_scene_id": scene.scene_id,
        "room_type": str(scene.extras["room_type"]) if "room_type" in scene.extras else None,
        "num_objects": scene.num_objects,
        "col_mesh": results["col_mesh"].rate,
        "grecall": results["grecall"].to_dict()["grecall"],
        "asd": results["asd"].to_dict()["asd"],
        "stability": stability.to_dict()["stability"],
        "still_fraction": stability.still_fraction,
        "displacement_ok_fraction": sum(stability.displacement_ok) / (stability.num_objects * stability.runs),
        "rotation_ok_fraction": sum(stability.rotation_ok) / (stability.num_objects * stability.runs),
        "details": {name: r.to_dict() for name, r in results.items()},
        "state": states,
        "fid_features": None if features is None else np.asarray(features, np.float64).tolist(),
        "seconds": seconds,
        "error": None,
    })
    return finite_or_none(record)


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
    records = []
    for path in paths:
        records.append(evaluate_scene(path, library, protocol, extractor))
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
    """
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
