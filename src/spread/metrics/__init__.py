"""SPREAD evaluation metrics (DESIGN §6) as torchmetrics classes, plus one per-scene function each.

| metric class | per-scene function | per-scene record | value |
|---|---|---|---|
| :class:`MeshCollisionRate` | :func:`scene_collisions` | :class:`CollisionResult` | Col_mesh, share of objects |
| :class:`GraphRecall` | :func:`scene_graph_recall` | :class:`GraphRecallResult` | GRecall, share of pairs |
| :class:`AverageSupportDistance` | :func:`scene_support_distance` | :class:`SupportDistanceResult` | ASD, metres |
| :class:`PhysicsStability` | :func:`scene_stability` | :class:`StabilityResult` | Stability and still shares |
| :class:`SceneFID` | :func:`fid_render` / :func:`scene_features` | features | FID or None + status |

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
from spread.metrics.stability import (  # noqa: F401
    STABILITY_DT, STABILITY_JITTER, STABILITY_RUNS, STABILITY_STEPS, STILL_ANGLE, STILL_DISTANCE,
    PhysicsStability, StabilityResult, scene_stability,
)
from spread.metrics.support_distance import (  # noqa: F401
    AverageSupportDistance, SupportDistanceResult, SupportPairDistance, scene_support_distance,
)
