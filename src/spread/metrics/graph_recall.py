"""GRecall (DESIGN §6): how many input spatial relations the generated poses actually realise.

Per scene (:func:`scene_graph_recall`): spatial codes are recomputed from the posed meshes with
:func:`spread.relations.scene_spatial_codes` (the one implementation of DESIGN §3) and compared with
the scene's ``spatial`` matrix — for a generated scene that is the conditioning graph. Every ordered
off-diagonal pair (i, j), i ≠ j, counts once: N(N − 1) pairs per scene.

Aggregate (:class:`GraphRecall`): matching pairs / pairs over all scenes, i.e. **pair-weighted** (a
20-object room weighs 380 pairs, a 3-object one 6), the same pooling as InstructScene's relation recall
(1 − errors / pairs over the test set). Scenes with one object have no pairs and change nothing.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from spread.metrics.base import SceneMetric, check_scene, ratio
from spread.metrics.registry import register_metric
from spread.relations import scene_spatial_codes


@dataclass
class GraphRecallResult:
    """GRecall of one scene: matching ordered pairs, pairs, and the mismatches [i, j, input, found]."""

    scene_id: str
    matches: int
    pairs: int
    mismatches: list[list[int]] = field(default_factory=list)

    @property
    def recall(self) -> float:
        return self.matches / self.pairs if self.pairs else float("nan")

    def to_dict(self) -> dict:
        return {"scene_id": self.scene_id, "grecall": self.recall if self.pairs else None,
                "matches": self.matches, "pairs": self.pairs, "mismatches": self.mismatches}


def scene_graph_recall(scene, library) -> GraphRecallResult:
    """GRecall of one scene (module docstring); raises on a scene that cannot be measured."""
    check_scene(scene, library)
    found = scene_spatial_codes(scene.translation, scene.rotation, [str(a) for a in scene.asset_id], library)
    off = ~np.eye(scene.num_objects, dtype=bool)
    wrong = off & (found != scene.spatial)
    mismatches = [[int(i), int(j), int(scene.spatial[i, j]), int(found[i, j])] for i, j in zip(*np.nonzero(wrong))]
    pairs = int(off.sum())
    return GraphRecallResult(scene.scene_id, pairs - len(mismatches), pairs, mismatches)


@register_metric("grecall", column="GRecall", digits=3, latex=r"GRecall$\uparrow$", default=True, order=10,
                 description="share of ordered object pairs whose spatial code is the graph's")
class GraphRecall(SceneMetric):
    """GRecall over many scenes, pair-weighted (higher is better).

    ``update(scenes, library)`` or ``update(graph_recall_results)``; ``compute()`` → float64 scalar
    tensor (NaN before any pair).
    """

    higher_is_better = True
    result_type = GraphRecallResult
    ratios = {"grecall": ("matches", "pairs")}
    counts = {"n_graph_pairs": "pairs"}

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self._add_sum_state("matches", dtype=torch.int64)
        self._add_sum_state("pairs", dtype=torch.int64)

    def evaluate(self, scene, library) -> GraphRecallResult:
        return scene_graph_recall(scene, library)

    def accumulate(self, result: GraphRecallResult) -> None:
        self._add("matches", result.matches)
        self._add("pairs", result.pairs)

    def compute(self) -> torch.Tensor:
        return ratio(self.matches, self.pairs)
