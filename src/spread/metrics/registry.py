"""The metric registry: every per-scene metric defined once, with what the rest of the platform needs to know.

A :class:`MetricSpec` is a metric's name (its key in ``metrics.json``, ``per_scene.jsonl``, tables, wandb), its
:class:`~spread.metrics.base.SceneMetric` class and factory, and how it is read: higher or lower is better, the
bootstrap unit, the table column, its display unit and scale (ASD is stored in metres and shown in mm
everywhere), digits. The evaluation protocol, its workers, aggregation, intervals, wandb, console tables,
``spread-report``, ``spread-ablate``, ``spread-compare`` and ``make demo`` iterate :data:`METRICS`.

Adding a metric is one file: a module in ``spread/metrics/`` whose class is decorated with
:func:`register_metric` (every module of this package is imported when the registry is first read), or, from
another package, an entry point in the group ``spread.metrics`` naming a ``SceneMetric`` subclass (its class
attributes ``higher_is_better``, ``column``, ``unit``, ``scale``, ``digits`` fill the spec) or a
:class:`MetricSpec`. ``spread-evaluate 'metrics=[grecall,<name>]'`` then selects it.

**Units live here.** Every value a metric writes to ``metrics.json`` is a :class:`ValueSpec` (the metric's own,
then its ``extra_values``: Stability's ``still_fraction``), which says how every table, CSV, plot axis, report and
sweep result shows it — stored value × ``scale`` in ``unit`` (ASD: metres stored, mm shown). The one table writer
(:mod:`spread.experiments.tables`) asks :func:`display_values`; nothing else converts units.

Set-level statistics (FID, KID) are not per-scene metrics: :data:`SET_METRICS` holds only their display.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

from spread.registry import Registry, RegistryError


@dataclass(frozen=True)
class ValueSpec:
    """One value of ``metrics.json`` (key ``name``) and its display (module docstring): header ``column``, display
    ``unit`` ("" for a share) and ``scale`` (display value = stored value × scale), ``digits``, ranking, LaTeX
    header, a one-line ``description``; ``shown``: a column of the printed tables (False: CSV, wandb tables and
    report files only); ``order``: position among the set-level values."""

    name: str
    column: str = ""
    unit: str = ""
    scale: float = 1.0
    digits: int = 3
    higher_is_better: bool = True
    latex: str | None = None
    description: str = ""
    shown: bool = True
    order: int = 1000

    @property
    def label(self) -> str:
        """Header with unit, e.g. ``ASD (mm)``."""
        title = self.column or self.name
        return f"{title} ({self.unit})" if self.unit else title

    @property
    def better(self) -> str:
        return "max" if self.higher_is_better else "min"

    def display(self, value) -> float | None:
        """A stored value in display units (None stays None)."""
        return None if value is None else float(value) * self.scale

    @property
    def key(self) -> str:
        """Its name in a table's header row (CSV, wandb): with the display unit when it has one (``asd_mm``)."""
        return unit_key(self.name, self.unit)


def unit_key(key: str, unit: str) -> str:
    """``key`` with its display unit, as table headers name a value shown in it (``asd`` in mm: ``asd_mm``)."""
    unit = "".join(c if c.isalnum() else "_" for c in unit)
    return f"{key}_{unit}" if unit else key


@dataclass(frozen=True)
class MetricSpec:
    """One registered metric (module docstring).

    name: key in every output. metric: the SceneMetric class. build: ``build(protocol) → metric`` (protocol: the
    :class:`~spread.evaluation.EvalProtocol`; default ``metric()``). higher_is_better: the ranking. column: table
    header. unit: display unit ("" for a share). scale: display value = stored value × scale. digits: decimals
    shown. latex: LaTeX header. default: in the default selection (today's four). order: position in tables.
    bootstrap_unit: what an interval resamples ("scene": every registered metric is a sum over scenes).
    description: one line for docs and ``--help``. extra_values: the other values its ``compute()`` reports that
    tables carry (:class:`ValueSpec`; Stability's ``still_fraction``)."""

    name: str
    metric: type
    build: Callable | None = None
    higher_is_better: bool = True
    column: str = ""
    unit: str = ""
    scale: float = 1.0
    digits: int = 3
    latex: str | None = None
    default: bool = False
    order: int = 100
    bootstrap_unit: str = "scene"
    description: str = ""
    extra_values: tuple = ()

    def create(self, protocol=None):
        """A fresh metric configured by ``protocol`` (None: the metric's own defaults)."""
        if self.build is not None and protocol is not None:
            return self.build(protocol)
        return self.metric()

    @property
    def value(self) -> ValueSpec:
        """The display of the metric's own value."""
        return ValueSpec(self.name, self.column, self.unit, self.scale, self.digits, self.higher_is_better, self.latex,
                         self.description, order=self.order)

    @property
    def values(self) -> tuple[ValueSpec, ...]:
        """Every value it reports that tables carry: its own, then :attr:`extra_values`."""
        return (self.value, *self.extra_values)

    label = property(lambda self: self.value.label, doc="Header with unit, e.g. ``ASD (mm)``.")
    better = property(lambda self: self.value.better)

    def display(self, value) -> float | None:
        """A stored value in display units (None stays None)."""
        return self.value.display(value)


def _adapt(name: str, obj) -> MetricSpec:
    """An entry point's object as a spec: a MetricSpec as it is, a SceneMetric subclass by its class attributes."""
    from spread.metrics.base import SceneMetric

    if isinstance(obj, MetricSpec):
        return obj if obj.name == name else MetricSpec(**{**obj.__dict__, "name": name})
    if isinstance(obj, type) and issubclass(obj, SceneMetric):
        return spec_of_class(name, obj)
    raise RegistryError(f"metric entry point '{name}': expected a spread.metrics.base.SceneMetric subclass or a "
                        f"MetricSpec, got {obj!r}")


def spec_of_class(name: str, cls: type, **fields) -> MetricSpec:
    """A spec from a SceneMetric class's attributes (``higher_is_better``, ``column``, ``unit``, ``scale``,
    ``digits``, ``latex``, ``description`` or its docstring's first line), ``fields`` overriding them."""
    doc = (cls.__doc__ or "").strip().splitlines()
    values = dict(higher_is_better=bool(getattr(cls, "higher_is_better", True)),
                  column=getattr(cls, "column", "") or name, unit=getattr(cls, "unit", ""),
                  scale=float(getattr(cls, "scale", 1.0)), digits=int(getattr(cls, "digits", 3)),
                  latex=getattr(cls, "latex", None), description=getattr(cls, "description", "") or (doc[0] if doc else ""))
    values.update(fields)
    return MetricSpec(name=name, metric=cls, **values)


METRICS: Registry[MetricSpec] = Registry("metric", "spread.metrics", packages=("spread.metrics",), adapt=_adapt)

SET_METRICS = (
    ValueSpec("fid", "FID", digits=2, higher_is_better=False, latex=r"FID$\downarrow$", order=1000,
              description="Fréchet distance of top-down render features to the reference set"),
    ValueSpec("kid", "KID", digits=4, higher_is_better=False, latex=r"KID$\downarrow$", order=1001,
              description="kernel (MMD) distance of the same features; unbiased, can be slightly below 0"),
)


def register_metric(name: str, **fields) -> Callable[[type], type]:
    """Class decorator: register a SceneMetric class as metric ``name`` (fields: :class:`MetricSpec`'s)."""
    def wrap(cls: type) -> type:
        METRICS.register(name, spec_of_class(name, cls, **fields), origin=f"{cls.__module__}.{cls.__qualname__}")
        return cls
    return wrap


def metric_spec(name: str) -> MetricSpec:
    return METRICS.get(name)


def ordered(specs) -> list:
    return sorted(specs, key=lambda s: s.order)


def all_metrics() -> list[MetricSpec]:
    """Every registered metric, in table order."""
    return ordered(spec for _, spec in METRICS.items())


def default_metric_names() -> list[str]:
    """The default selection (today's four: Col_mesh, GRecall, ASD, Stability), in registration order."""
    return [name for name, spec in METRICS.items() if spec.default]


def selected_metrics(names: Sequence[str] | None = None) -> list[MetricSpec]:
    """The specs of ``names`` (None: the default selection), in the order given; unknown or repeated names are
    an error naming them."""
    names = default_metric_names() if names is None else list(names)
    if not names:
        raise RegistryError(f"metrics: choose at least one of {METRICS.names()}")
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise RegistryError(f"metrics: {twice} named twice")
    return [METRICS.get(str(n)) for n in names]


def display_specs(names: Sequence[str] | None = None, with_set: bool = True) -> list:
    """What a results table shows: the selected metrics in table order, then FID and KID."""
    specs = ordered(selected_metrics(names))
    return specs + (list(SET_METRICS) if with_set else [])


def display_values(names: Sequence[str] | None = None, with_set: bool = True) -> list[ValueSpec]:
    """Every value a results table carries (module docstring): each selected metric's values (:attr:`MetricSpec.values`,
    Stability's ``still_fraction`` too) in table order, then FID and KID."""
    return [v for spec in ordered(selected_metrics(names)) for v in spec.values] + (list(SET_METRICS) if with_set else [])


def value_spec(name: str) -> ValueSpec | None:
    """The display of a value by its ``metrics.json`` key: a metric's own or extra value, FID, KID (None: none)."""
    for spec in SET_METRICS:
        if spec.name == name:
            return spec
    for _, spec in METRICS.items():
        for value in spec.values:
            if value.name == name:
                return value
    return None


def display_spec(name: str):
    """The display of a metric or set metric by name (None for neither)."""
    for spec in SET_METRICS:
        if spec.name == name:
            return spec
    return METRICS.get(name) if name in METRICS else None
