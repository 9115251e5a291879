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

from spread.metrics.base import SceneMetric, check_scene, scene_seed  # noqa: F401
from spread.metrics.collision import (  # noqa: F401
    COLLISION_DEPTH_THRESHOLD, CollisionResult, MeshCollisionRate, PairDepth, scene_collisions,
)
from spread.metrics.extractors import FEATURE_DIMS, ExtractorStatus, load_extractor  # noqa: F401
from spread.metrics.fid import FID_RENDER_SETTINGS, SceneFID, fid_render, scene_features  # noqa: F401
from spread.metrics.graph_recall import GraphRecall, GraphRecallResult, scene_graph_recall  # noqa: F401
from spread.metrics.support_distance import (  # noqa: F401
    AverageSupportDistance, SupportDistanceResult, SupportPairDistance, scene_support_distance,
)
from spread.metrics.stability import (  # noqa: F401
    STABILITY_DT, STABILITY_JITTER, STABILITY_RUNS, STABILITY_STEPS, STILL_ANGLE, STILL_DISTANCE,
    PhysicsStability, StabilityResult, scene_stability,
)
from spread.metrics.out_of_bounds import OutOfBoundsRate, scene_out_of_bounds  # noqa: F401
from spread.metrics.registry import (  # noqa: F401
    METRICS, MetricSpec, default_metric_names, display_specs, register_metric, selected_metrics,
)
