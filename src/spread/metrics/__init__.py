"""SPREAD evaluation metrics (DESIGN §6) as torchmetrics classes, plus one per-scene function each.

| metric class | per-scene function | per-scene record | value |
|---|---|---|---|
| :class:`MeshCollisionRate` | :func:`scene_collisions` | :class:`CollisionResult` | Col_mesh, share of objects |
| :class:`GraphRecall` | :func:`scene_graph_recall` | :class:`GraphRecallResult` | GRecall, share of pairs |
| :class:`AverageSupportDistance` | :func:`scene_support_distance` | :class:`SupportDistanceResult` | ASD, metres |
| :class:`PhysicsStability` | :func:`scene_stability` | :class:`StabilityResult` | Stability and still shares |
| :class:`OutOfBoundsRate` | :func:`scene_out_of_bounds` | :class:`OutOfBoundsResult` | OOB, share of objects |
| :class:`SceneFID` | :func:`fid_render` / :func:`scene_features` | features | FID or None + status |

Every per-scene metric is registered once (:mod:`spread.metrics.registry`, :data:`METRICS`: name, class,
factory, ranking, display); the platform iterates the registry, and plugins add metrics through the entry-point
group ``spread.metrics``.

Usage: ``metric.update(scenes, library)`` or ``metric.update(per_scene_records)``; ``metric.compute()``.
States are tensors summed across DDP ranks and mergeable with ``metric.merge_state(other)`` (see
:mod:`spread.metrics.base`). Per-scene functions raise ``SceneFormatError`` (a ``ValueError``) on a
scene that cannot be measured; each record's ``to_dict()`` is one JSON line of ``per_scene.jsonl``.
"""

from spread.lazy import lazy_names

#: Every public name and the module that defines it, imported on first access (PEP 562): ``import
#: spread.metrics.registry`` and the protocol's constants do not pay for torch and torchmetrics.
_EXPORTS = {
    "spread.metrics.base": ("SceneMetric", "check_scene", "scene_seed"),
    "spread.metrics.constants": (
        "COLLISION_DEPTH_THRESHOLD", "FID_RENDER_SETTINGS", "STABILITY_DT", "STABILITY_JITTER", "STABILITY_RUNS",
        "STABILITY_STEPS", "STILL_ANGLE", "STILL_DISTANCE",
    ),
    "spread.metrics.collision": ("CollisionResult", "MeshCollisionRate", "PairDepth", "scene_collisions"),
    "spread.metrics.extractors": ("FEATURE_DIMS", "ExtractorStatus", "load_extractor"),
    "spread.metrics.fid": ("SceneFID", "fid_render", "scene_features"),
    "spread.metrics.graph_recall": ("GraphRecall", "GraphRecallResult", "scene_graph_recall"),
    "spread.metrics.support_distance": (
        "AverageSupportDistance", "SupportDistanceResult", "SupportPairDistance", "scene_support_distance",
    ),
    "spread.metrics.stability": ("PhysicsStability", "StabilityResult", "scene_stability"),
    "spread.metrics.out_of_bounds": ("OutOfBoundsRate", "scene_out_of_bounds"),
    "spread.metrics.registry": (
        "METRICS", "MetricSpec", "default_metric_names", "display_specs", "register_metric", "selected_metrics",
    ),
}
__getattr__, __dir__ = lazy_names(__name__, _EXPORTS)
