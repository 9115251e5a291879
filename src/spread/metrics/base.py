"""What every SPREAD metric shares: a torchmetrics base class with summed states, input checks, seeds.

Every metric is computed in two layers:

* a plain **per-scene function** (``scene_collisions``, ``scene_graph_recall``, ...) that checks the
  scene, computes the scene's value and its diagnostics and returns a small result record with
  ``to_dict()`` (one line of ``per_scene.jsonl``); it raises on bad input (see :func:`check_scene`);
* a :class:`torchmetrics.Metric` that **accumulates** those results into sum states.

Every state is a tensor summed across processes (``dist_reduce_fx="sum"``), so the aggregate is the
same whether scenes are split over DDP ranks (``sync``), over Ray workers (ship
``metric.metric_state`` or the per-scene results back and ``merge_state`` / ``update`` on the driver),
or not split at all. No mean or concatenation states: sums are exact to merge in any order.

The asset library is passed to ``update`` (``metric.update(scenes, library)``), not to the
constructor: a metric then holds only numbers, so it pickles, deep-copies and travels to Ray workers
without dragging meshes and locks along. ``update`` also accepts the per-scene result records instead
of scenes (no library needed), which is how a driver accumulates what workers computed.
"""

from __future__ import annotations

import hashlib
import math
from typing import Any, Iterable, Sequence

import torch
from torchmetrics import Metric

from spread.scene import Scene, validate_scene


def check_scene(scene: Scene, library) -> None:
    """Raise :class:`~spread.scene.SceneFormatError` (a ``ValueError``) naming the scene, key and problem
    when ``scene`` cannot be measured: no objects, NaN/inf poses, non-rotations, bad codes, or an
    asset the library does not have (the message names the asset)."""
    if not isinstance(scene, Scene):
        raise TypeError(f"expected a spread.scene.Scene, got {type(scene).__name__}")
    validate_scene(scene, source=f"scene '{scene.scene_id}'", assets=library)


class MetricOutputError(ValueError):
    """A metric that reported something it may not (another name, not a number, ±inf); names the metric."""


def scene_seed(scene_id: str, base_seed: int = 0) -> int:
    """A 32-bit seed from the scene id (sha256), so per-scene randomness does not depend on worker order."""
    digest = hashlib.sha256(f"{int(base_seed)}:{scene_id}".encode("utf-8")).digest()
    return int.from_bytes(digest[:4], "little")


class SceneMetric(Metric):
    """Base of the SPREAD metrics: sum states, ``update(items, library)`` over scenes or result records.

    Subclasses set ``result_type`` (the per-scene record), implement :meth:`evaluate` (scene → record,
    the per-scene function) and :meth:`accumulate` (record → states), and declare ``ratios``: each value
    ``compute()`` reports that is a pooled ratio of two sum states (value → (numerator state, denominator state)),
    which is how the bootstrap over scenes asks a metric for its per-scene terms (:meth:`pooled_terms`) without
    reading its states itself. ``reports`` names any other value ``compute()`` returns (Stability's
    ``displacement_ok_fraction``): a metric reports its name, its ``ratios`` and its ``reports``, nothing else
    (:meth:`values` refuses any other key). ``counts`` names sum states reported as integers in ``metrics.json``
    (``n_<what>`` → state). Display attributes (``column``, ``unit``, ``scale``, ``digits``) are read by
    :func:`spread.metrics.registry.spec_of_class` for plugins registered by class.
    """

    full_state_update = False
    is_differentiable = False
    result_type: type = object
    ratios: dict[str, tuple[str, str]] = {}
    reports: tuple[str, ...] = ()
    counts: dict[str, str] = {}

    def _add_sum_state(self, name: str, shape: tuple[int, ...] = (), dtype: torch.dtype = torch.float64) -> None:
        self.add_state(name, default=torch.zeros(shape, dtype=dtype), dist_reduce_fx="sum")

    def _add(self, name: str, value: Any) -> None:
        state = getattr(self, name)
        setattr(self, name, state + torch.as_tensor(value, dtype=state.dtype, device=state.device))

    def evaluate(self, scene: Scene, library):  # pragma: no cover - abstract
        raise NotImplementedError

    def accumulate(self, result) -> None:  # pragma: no cover - abstract
        raise NotImplementedError

    def update(self, items: Sequence[Any] | Any, library=None) -> None:
        """Add scenes (measured with ``library``) or per-scene result records to the states."""
        for result in self._results(items, library):
            self.accumulate(result)

    def _results(self, items, library) -> Iterable:
        if isinstance(items, (Scene, self.result_type)):
            items = [items]
        for item in items:
            if isinstance(item, self.result_type):
                yield item
            elif isinstance(item, Scene):
                if library is None:
                    raise ValueError(f"{type(self).__name__}.update: scenes need the asset library "
                                     f"(update(scenes, library))")
                yield self.evaluate(item, library)
            else:
                raise TypeError(f"{type(self).__name__}.update: expected Scene or {self.result_type.__name__}, "
                                f"got {type(item).__name__}")

    def values(self, name: str) -> dict[str, float]:
        """``compute()`` as plain floats (NaN where nothing was measured): ``{name: value}`` for a metric of one
        value, the dict's own keys for one of several (Stability: ``stability``, ``still_fraction``, ...).
        :class:`MetricOutputError` naming the metric when ``compute()`` returns a name that is not its own
        (``name``, :attr:`ratios`, :attr:`reports`: another metric's ``grecall``, a record's ``scene_id``), a
        value that is not a number, or ±inf."""
        out = self.compute()
        own = {name, *self.ratios, *self.reports}
        items = out.items() if isinstance(out, dict) else [(name, out)]
        values = {}
        for key, value in items:
            if key not in own:
                raise MetricOutputError(f"metric '{name}': compute() returned {key!r}, which is not one of its own "
                                        f"names {sorted(own)} (declare it in 'ratios' or 'reports')")
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise MetricOutputError(f"metric '{name}': compute() returned {type(value).__name__} for {key!r}, "
                                        f"not a number") from None
            if math.isinf(number):
                raise MetricOutputError(f"metric '{name}': compute() returned {number} for {key!r}")
            values[key] = number
        return values

    def pooled_terms(self, state: dict) -> dict[str, tuple[float, float]]:
        """value → (numerator, denominator) of one scene's states (``per_scene.jsonl``'s ``state[name]``), for
        every value in :attr:`ratios`; the bootstrap resamples scenes and pools these."""
        try:
            return {value: (float(state[num]), float(state[den])) for value, (num, den) in self.ratios.items()}
        except (KeyError, TypeError) as exc:
            raise ValueError(f"{type(self).__name__}: per-scene state without {exc!s} (evaluated with another "
                             f"version: evaluate again)") from None

    def count_values(self) -> dict[str, int]:
        """The integer counts this metric reports (:attr:`counts`), from its summed states."""
        return {key: int(getattr(self, state)) for key, state in self.counts.items()}

    def merge_state(self, incoming_state) -> None:
        """Add another metric's (or a ``metric_state`` dict's) sums to this one's, then drop the cached value."""
        super().merge_state(incoming_state)
        self._computed = None
        self._update_count += 1  # merged data counts as an update (no "compute before update" warning)


def ratio(numerator: torch.Tensor, denominator: torch.Tensor) -> torch.Tensor:
    """numerator / denominator as float64, NaN when the denominator is 0 (nothing was measured)."""
    num, den = numerator.double(), denominator.double()
    return torch.where(den > 0, num / den.clamp_min(1), torch.full_like(num, float("nan")))
