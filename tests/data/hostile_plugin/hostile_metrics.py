"""Metric plugins that lie, edit or break, for tests/test_hostile_round4.py (issue 32). Each is a real
``SceneMetric`` reached through the ``spread.metrics`` entry points of ``hostile_metrics-0.1.dist-info``, as an
installed package's would be. ``honest`` is the control: objects per scene, correctly declared."""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
import torch

from spread.metrics.base import SceneMetric, ratio


@dataclass
class Count:
    scene_id: str
    objects: int
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"scene_id": self.scene_id, "objects": self.objects, **self.extra}


def counting(name: str, evaluate=None, compute=None, extra=None):
    """A metric class ``name``: objects per scene (pooled: Σ objects / Σ scenes), with its misbehaviour."""

    class Metric(SceneMetric):
        result_type = Count
        unit = "objects"
        ratios = {name: ("objects", "scenes")}

        def __init__(self, **kwargs):
            super().__init__(**kwargs)
            self._add_sum_state("objects", dtype=torch.int64)
            self._add_sum_state("scenes", dtype=torch.int64)

        def evaluate(self, scene, library):
            if evaluate is not None:
                evaluate(scene)
            return Count(scene.scene_id, scene.num_objects, dict(extra or {}))

        def accumulate(self, result):
            self._add("objects", result.objects)
            self._add("scenes", 1)

        def compute(self):
            value = ratio(self.objects, self.scenes)
            return value if compute is None else compute(value)

    Metric.__name__ = Metric.__qualname__ = name.title().replace("_", "")
    return Metric


def move_up(scene):
    scene.translation[:, 1] += 0.5  # in place: what the next metric would see


def erase_graph(scene):
    scene.spatial[:] = 0  # GRecall's ground truth, in place


def rebind(scene):
    scene.translation = scene.translation + np.float32([0.0, 5.0, 0.0])  # a new array on its own copy: allowed
    scene.spatial = np.zeros_like(scene.spatial)


def fail_on_one(scene):
    if scene.scene_id == os.environ.get("HOSTILE_FAIL_SCENE"):
        raise RuntimeError(f"cannot measure {scene.scene_id}")


Honest = counting("honest")
Liar = counting("liar", compute=lambda v: {"liar": v, "grecall": torch.tensor(0.999, dtype=torch.float64)})
Liar2 = counting("liar2", compute=lambda v: {"liar2": v, "stability": torch.tensor(1.0, dtype=torch.float64)})
Mover = counting("mover", evaluate=move_up)
SpatialEraser = counting("spatial_eraser", evaluate=erase_graph)
Rebinder = counting("rebinder", evaluate=rebind)
Arrayed = counting("arrayed", extra={"positions": np.arange(3)})
Setty = counting("setty", extra={"ids": {1, 2}})
Raiser = counting("raiser", evaluate=fail_on_one)
Infinite = counting("infinite", compute=lambda v: torch.tensor(float("inf"), dtype=torch.float64))
