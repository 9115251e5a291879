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
(:mod:`spread.reporting.tables`) asks :func:`display_values`; nothing else converts units.

Set-level statistics (FID, KID) are not per-scene metrics: :data:`SET_METRICS` holds only their display.

**A metric reports only its own names** (:func:`own_names`: its name, its ``ratios`` and ``reports`` values, its
``counts``), which share one namespace with the fields of ``per_scene.jsonl`` records and ``metrics.json``. A
metric whose names collide with those fields (:data:`RESERVED_NAMES`, and the patterns of
:func:`reserved_reason`: ``n_*`` is for counts, ``*_lo``/``*_hi`` for intervals) or with another metric's is
refused when it registers (a plugin: listed as failed, the others load), so no plugin can overwrite GRecall in
``metrics.json`` or the ``scene_id`` of every record.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
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
    #: (low, high) of a valid stored value (None: any finite number); tables show a value outside as invalid.
    bounds: tuple[float, float] | None = None

    @property
    def valid_range(self) -> tuple[float, float] | None:
        """(low, high) of a valid stored value (:attr:`bounds`)."""
        return None if self.bounds is None else (float(self.bounds[0]), float(self.bounds[1]))

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


#: The columns beside a value that share its unit: its interval's bounds and its standard deviation over seeds.
SCALED_SUFFIXES = ("_lo", "_hi", "_sd")


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
    description: one line for docs and ``--help``. bounds: (low, high) of a valid stored value (None: a share,
    ``unit`` "", lies in [0, 1]; any other metric only needs to be finite): tables show a value outside them as
    invalid, never as the best. extra_values: the other values its ``compute()`` reports that tables carry
    (:class:`ValueSpec`; Stability's ``still_fraction``)."""

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
    bounds: tuple[float, float] | None = None
    extra_values: tuple = ()

    @property
    def valid_range(self) -> tuple[float, float] | None:
        """(low, high) of a valid stored value: :attr:`bounds`, else [0, 1] for a share (``unit`` "")."""
        if self.bounds is not None:
            return (float(self.bounds[0]), float(self.bounds[1]))
        return (0.0, 1.0) if not self.unit else None

    def create(self, protocol=None):
        """A fresh metric configured by ``protocol`` (None: the metric's own defaults)."""
        if self.build is not None and protocol is not None:
            return self.build(protocol)
        return self.metric()

    @property
    def value(self) -> ValueSpec:
        """The display of the metric's own value."""
        return ValueSpec(self.name, self.column, self.unit, self.scale, self.digits, self.higher_is_better, self.latex,
                         self.description, order=self.order, bounds=self.valid_range)

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
                  latex=getattr(cls, "latex", None), description=getattr(cls, "description", "") or (doc[0] if doc else ""),
                  bounds=getattr(cls, "bounds", None))
    values.update(fields)
    return MetricSpec(name=name, metric=cls, **values)


#: Fields of a ``per_scene.jsonl`` record besides its metrics' values (``spread.evaluation.work``).
RECORD_FIELDS = frozenset({
    "scene_id", "file", "node_id", "pid", "input_sha256", "error", "error_type", "traceback", "seconds",
    "inner_scene_id", "room_type", "num_objects", "details", "state", "fid_features", "metric_errors"})
#: Fields of ``metrics.json`` besides its metrics' values, and of the rows that reports and sweeps build from it.
SUMMARY_FIELDS = frozenset({
    "n_scenes", "n_evaluated", "n_failed", "n_implausible", "n_refused_inputs", "n_objects", "n_metric_failures",
    "per_room_type", "bootstrap", "fid", "kid", "fid_status", "fid_feature_model", "fid_num_generated",
    "fid_num_reference", "kid_subsets", "kid_subset_size", "failed", "metric_failures", "failed_metrics", "fid_reference_failed",
    "invalid_values", "scenes", "reference", "reference_split", "protocol", "versions", "redone_because", "run",
    "source", "kind", "variant", "method", "method_key", "status", "point", "reused", "best", "trial_seconds",
    "node", "trial_pid", "startup_seconds", "fingerprint", "ci_level", "ci_resamples", "ci_seed", "ci_few"})
#: Names no metric may report (module docstring).
RESERVED_NAMES = RECORD_FIELDS | SUMMARY_FIELDS


def reserved_reason(name: str, count: bool = False) -> str | None:
    """Why ``name`` may not be a metric's value (``count=False``) or count (``count=True``) name, or None."""
    if name in RECORD_FIELDS:
        return "a field of every per_scene.jsonl record"
    if name in SUMMARY_FIELDS:
        return "a field of metrics.json"
    if name.endswith(("_lo", "_hi", "_sd")):
        return "the '_lo'/'_hi'/'_sd' suffixes name a metric's interval and spread"
    if name.startswith(("fid_", "kid_")):
        return "the 'fid_'/'kid_' prefixes belong to the set-level FID and KID"
    if count and not name.startswith("n_"):
        return "a count's name starts with 'n_'"
    if not count and name.startswith("n_"):
        return "the 'n_' prefix names counts"
    return None


def own_names(spec: MetricSpec) -> tuple[set[str], set[str]]:
    """(value names, count names) a metric reports: its name, the values of its ``ratios`` and ``reports`` (what
    ``compute()`` returns), and its ``counts``."""
    cls = spec.metric
    values = {spec.name, *dict(getattr(cls, "ratios", {}) or {}), *tuple(getattr(cls, "reports", ()) or ())}
    return values, set(dict(getattr(cls, "counts", {}) or {}))


def check_spec(name: str, spec, others: dict) -> None:
    """:class:`RegistryError` when ``spec`` may not be registered as ``name`` (module docstring): a name of its
    is reserved, or another metric reports it."""
    if not isinstance(spec, MetricSpec):
        raise RegistryError(f"metric '{name}': expected a MetricSpec, got {type(spec).__name__}")
    if spec.default and name not in DEFAULT_METRICS:
        raise RegistryError(f"metric '{name}' refused: default=True, but the default selection is DESIGN §6's "
                            f"{list(DEFAULT_METRICS)}; register it without default and choose it by name "
                            f"(protocol.metrics=[{', '.join(DEFAULT_METRICS)}, {name}])")
    values, counts = own_names(spec)
    for names, count in ((values, False), (counts, True)):
        for n in sorted(names):
            why = reserved_reason(str(n), count)
            if why:
                raise RegistryError(f"metric '{name}' refused: it would report '{n}', which is {why}; rename it")
    for other, held in others.items():
        clash = sorted((values | counts) & set().union(*own_names(held)))
        if clash:
            raise RegistryError(f"metric '{name}' refused: it would report {clash}, which metric '{other}' reports; "
                                f"rename it")


#: The built-in metrics' modules, in the order of their entries (the default selection Col_mesh, GRecall, ASD,
#: Stability, then OOB), whichever of them a process imports first; then any other module of the package.
BUILTIN_MODULES = ("spread.metrics.collision", "spread.metrics.graph_recall", "spread.metrics.support_distance",
                   "spread.metrics.stability", "spread.metrics.out_of_bounds")
METRICS: Registry[MetricSpec] = Registry("metric", "spread.metrics", packages=(*BUILTIN_MODULES, "spread.metrics"),
                                         adapt=_adapt, check=check_spec)

SET_METRICS = (
    ValueSpec("fid", "FID", digits=2, higher_is_better=False, latex=r"FID$\downarrow$", order=1000,
              description="Fréchet distance of top-down render features to the reference set", bounds=(0.0, math.inf)),
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


#: The default selection (DESIGN §6: Col_mesh, GRecall, ASD, Stability), by name, so the command schemas know their
#: ``protocol.metrics`` default without importing a metric (every metric module imports torchmetrics: ~2.5 s of a
#: console script's start). The built-ins that say ``default=True`` are exactly these; another metric is chosen by
#: name (``protocol.metrics=[...]``), and a plug-in that says ``default=True`` is refused (:func:`check_spec`).
DEFAULT_METRICS = ("col_mesh", "grecall", "asd", "stability")


def default_metric_names() -> list[str]:
    """The default selection (:data:`DEFAULT_METRICS`), in table order; imports no metric."""
    return list(DEFAULT_METRICS)


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


def _split_bound(key: str) -> tuple[str, str]:
    for end in SCALED_SUFFIXES:
        if key.endswith(end):
            return key[: -len(end)], end
    return key, ""


def in_display_units(values: dict) -> dict:
    """Flat scalars keyed as ``metrics.json`` keys them (a value, its ``_lo``/``_hi``, its ``_sd`` over seeds) in
    their display units, keyed as a table's header names them (``asd`` in m → ``asd_mm`` in mm: :attr:`ValueSpec.key`), for the trackers
    (wandb summaries, MLflow metrics); a key of no value with a unit is kept as it is. :func:`in_stored_units`
    reads them back."""
    out = {}
    for key, value in values.items():
        base, end = _split_bound(str(key))
        spec = value_spec(base) if end else value_spec(str(key))
        if spec is None or not spec.unit:
            out[key] = value
        else:
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            out[f"{spec.key}{end}"] = spec.display(value) if number else value
    return out


def in_stored_units(values: dict) -> dict:
    """:func:`in_display_units`'s scalars back as ``metrics.json`` keys and units (``asd_mm`` in mm → ``asd`` in
    m); a key already stored so (a run logged before the trackers took display units) is kept as it is."""
    by_key = {spec.key: spec for _, metric in METRICS.items() for spec in metric.values if spec.unit}
    by_key |= {spec.key: spec for spec in SET_METRICS if spec.unit}
    out = {}
    for key, value in values.items():
        base, end = _split_bound(str(key))
        spec = by_key.get(base) if end else by_key.get(str(key))
        if spec is None or (spec.name + end) in values:
            out[key] = value
        else:
            number = isinstance(value, (int, float)) and not isinstance(value, bool)
            out[f"{spec.name}{end}"] = float(value) / spec.scale if number else value
    return out


def display_spec(name: str):
    """The display of a metric or set metric by name (None for neither)."""
    for spec in SET_METRICS:
        if spec.name == name:
            return spec
    return METRICS.get(name) if name in METRICS else None
