"""Out-of-bounds rate (``oob``): the share of objects whose footprint leaves the room's floor, as SceneEval reports.

An object's footprint is the xz projection of its posed convex hull (world frame, metres; y is up, DESIGN §3).
It leaves the floor when some hull vertex lies more than ``tolerance`` (default 1 cm) outside the room's
floor rectangle ``room[0].xz … room[1].xz`` (the scene file's ``room`` bounds). Scenes without ``room`` bounds
are not measured (they add no objects), as ASD skips rooms without support pairs. Lower is better; pooled
over scenes (out-of-bounds objects / measured objects), so its interval is a bootstrap over scenes.

Selected by name: ``spread-evaluate 'metrics=[col_mesh,grecall,asd,stability,oob]'``. Defined in this one
file through the metric registry (issue 22's worked example of a new metric).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from spread.metrics.base import SceneMetric, check_scene, ratio
from spread.metrics.registry import register_metric
from spread.relations import hull_vertices

#: Metres a hull vertex may stick out of the floor rectangle before the object counts as out of bounds.
OOB_TOLERANCE = 0.01


@dataclass
class OutOfBoundsResult:
    """One scene: which objects leave the floor, and by how much (metres, the largest excess per object)."""

    scene_id: str
    num_objects: int
    measured: bool  # False: the scene has no room bounds
    outside: list[bool] = field(default_factory=list)
    excess: list[float] = field(default_factory=list)
    tolerance: float = OOB_TOLERANCE

    @property
    def num_outside(self) -> int:
        return int(sum(self.outside))

    def to_dict(self) -> dict:
        rate = self.num_outside / self.num_objects if self.measured and self.num_objects else None
        return {"scene_id": self.scene_id, "oob": rate, "measured": self.measured, "num_objects": self.num_objects,
                "outside": [i for i, o in enumerate(self.outside) if o], "excess": self.excess,
                "tolerance": self.tolerance}


def footprint_excess(vertices: np.ndarray, room: np.ndarray) -> float:
    """Metres by which the xz footprint of world ``vertices`` (V, 3) leaves the floor rectangle of ``room`` (2, 3);
    0 when it stays inside."""
    xz = vertices[:, [0, 2]]
    lo, hi = room[0, [0, 2]], room[1, [0, 2]]
    return float(max(0.0, (lo - xz).max(), (xz - hi).max()))


def scene_out_of_bounds(scene, library, tolerance: float = OOB_TOLERANCE) -> OutOfBoundsResult:
    """:class:`OutOfBoundsResult` of one scene (module docstring); raises on a scene that cannot be measured."""
    check_scene(scene, library)
    if scene.room is None:
        return OutOfBoundsResult(scene.scene_id, scene.num_objects, measured=False, tolerance=tolerance)
    room = np.asarray(scene.room, np.float64)
    excess = []
    for k, asset in enumerate(scene.asset_id):
        local = hull_vertices(library, str(asset))
        world = local @ np.asarray(scene.rotation[k], np.float64).T + np.asarray(scene.translation[k], np.float64)
        excess.append(footprint_excess(world, room))
    return OutOfBoundsResult(scene.scene_id, scene.num_objects, True, [e > tolerance for e in excess], excess,
                             tolerance)


@register_metric("oob", column="OOB", digits=3, latex=r"OOB$\downarrow$", order=50,
                 description="share of objects whose footprint leaves the room's floor bounds (SceneEval)")
class OutOfBoundsRate(SceneMetric):
    """Out-of-bounds objects / objects of the scenes with room bounds (lower is better; NaN before any)."""

    higher_is_better = False
    result_type = OutOfBoundsResult
    ratios = {"oob": ("outside_objects", "objects")}
    counts = {"n_oob_objects": "outside_objects"}

    def __init__(self, tolerance: float = OOB_TOLERANCE, **kwargs):
        super().__init__(**kwargs)
        self.tolerance = float(tolerance)
        self._add_sum_state("outside_objects", dtype=torch.int64)
        self._add_sum_state("objects", dtype=torch.int64)

    def evaluate(self, scene, library) -> OutOfBoundsResult:
        return scene_out_of_bounds(scene, library, self.tolerance)

    def accumulate(self, result: OutOfBoundsResult) -> None:
        if result.measured:
            self._add("outside_objects", result.num_outside)
            self._add("objects", result.num_objects)

    def compute(self) -> torch.Tensor:
        return ratio(self.outside_objects, self.objects)
