"""ASD, average support distance (DESIGN §6): how far supported objects are from their supporters.

Per scene (:func:`scene_support_distance`), for each support pair of the scene's ``physical`` graph
(``physical[i, j] == 1``: i supports j; for a generated scene, the conditioning graph): j's vertices and
surface samples are posed, moved into i's frame, and their signed distances to i's watertight mesh
computed (positive outside, metres). The pair's value is the minimum: ≈ 0 when j rests on i, the gap
when j floats above it, minus the penetration when j sinks into it. The scene's ASD is the mean of
|min| over its pairs (exact minimum over the point set, see
:func:`spread.metrics.geometry.min_signed_distance`). Pairs whose supported object is a wall or ceiling
mount (:func:`spread.scene.welded_objects`: held by the building, not resting) are left out.

Aggregate (:class:`AverageSupportDistance`): Σ|min| / number of pairs over all scenes (pair-weighted),
metres; scenes without support pairs contribute nothing; NaN before any pair.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from spread.metrics.base import SceneMetric, check_scene, ratio
from spread.metrics.registry import register_metric
from spread.metrics.geometry import asset_geometry, min_signed_distance, to_local, to_world


@dataclass
class SupportPairDistance:
    """One support pair: supporter i, supported j, min signed distance of j to i (metres, + outside)."""

    supporter: int
    supported: int
    min_signed_distance: float

    def to_dict(self) -> dict:
        return {"supporter": self.supporter, "supported": self.supported,
                "min_signed_distance": self.min_signed_distance}


@dataclass
class SupportDistanceResult:
    """ASD of one scene: one entry per support pair of its input graph."""

    scene_id: str
    pairs: list[SupportPairDistance] = field(default_factory=list)

    @property
    def abs_sum(self) -> float:
        return float(sum(abs(p.min_signed_distance) for p in self.pairs))

    @property
    def asd(self) -> float:
        return self.abs_sum / len(self.pairs) if self.pairs else float("nan")

    def to_dict(self) -> dict:
        return {"scene_id": self.scene_id, "asd": self.asd if self.pairs else None,
                "num_pairs": len(self.pairs), "pairs": [p.to_dict() for p in self.pairs]}


def support_gap(scene, library, supporter: int, supported: int) -> float:
    """Min signed distance (metres, positive outside) of ``supported``'s points to ``supporter``'s mesh."""
    gi = asset_geometry(library, str(scene.asset_id[supporter]))
    gj = asset_geometry(library, str(scene.asset_id[supported]))
    Ri, ti = scene.rotation[supporter].astype(np.float64), scene.translation[supporter].astype(np.float64)
    Rj, tj = scene.rotation[supported].astype(np.float64), scene.translation[supported].astype(np.float64)
    d, _ = min_signed_distance(gi, to_local(to_world(gj.points, Rj, tj), Ri, ti))
    return d


def scene_support_distance(scene, library) -> SupportDistanceResult:
    """ASD of one scene (module docstring); raises on a scene that cannot be measured."""
    from spread.scene import welded_objects

    check_scene(scene, library)
    welded = welded_objects(scene)
    pairs = [SupportPairDistance(int(i), int(j), support_gap(scene, library, int(i), int(j)))
             for i, j in scene.support_pairs() if not welded[j]]
    return SupportDistanceResult(scene.scene_id, pairs)


@register_metric("asd", column="ASD", unit="mm", scale=1000.0, digits=1, latex=r"ASD (mm)$\downarrow$", default=True,
                 order=30, bounds=(0.0, float("inf")),
                 description="mean |signed distance| of supported objects to their supporters (stored in m)")
class AverageSupportDistance(SceneMetric):
    """ASD over many scenes, metres, pair-weighted (lower is better).

    ``update(scenes, library)`` or ``update(support_distance_results)``; ``compute()`` → float64 scalar
    tensor (NaN before any support pair).
    """

    higher_is_better = False
    result_type = SupportDistanceResult
    ratios = {"asd": ("abs_distance_sum", "pairs")}
    counts = {"n_support_pairs": "pairs"}

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._add_sum_state("abs_distance_sum")
        self._add_sum_state("pairs", dtype=torch.int64)

    def evaluate(self, scene, library) -> SupportDistanceResult:
        return scene_support_distance(scene, library)

    def accumulate(self, result: SupportDistanceResult) -> None:
        self._add("abs_distance_sum", result.abs_sum)
        self._add("pairs", len(result.pairs))

    def compute(self) -> torch.Tensor:
        return ratio(self.abs_distance_sum, self.pairs)
