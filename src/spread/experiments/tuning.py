"""The sweep's search algorithms and trial schedulers, chosen by registered name (Ray Tune's own ``search_alg`` and
``scheduler`` objects, made by name as Ray Tune's examples pick them).

A :class:`SearchSpec` is a name (``spread-sweep search=<name>``) and ``build(settings) → a Ray Tune searcher`` (None:
Tune's own variant generation), ``grid``: every combination of the values once (then ``interval()`` is refused
and ``num_samples`` is 1). Built-ins: ``grid``, ``random`` (Tune's ``BasicVariantGenerator`` seeded by
``search_seed``), ``optuna`` (``OptunaSearch``, TPE). A :class:`TrialSchedulerSpec` is a name
(``scheduler=<name>``) and ``build(settings)``; built-in: ``asha`` (``ASHAScheduler`` on each validation, its
``asha`` settings). ``settings`` is the sweep's :class:`~spread.experiments.sweep.SweepSettings` (``metric``,
``mode``, ``search_seed``, ``asha``, ...). Whatever a search builds, the sweep runs it through :func:`limited`, so
``max_concurrent`` holds for every search and scheduler.

Another one is chosen without editing this file: an entry point in the group ``spread.searchers`` (or
``spread.trial_schedulers``) naming a spec, or a ``"module:Class"`` target of any Ray Tune searcher or scheduler
class, built as ``Class(metric=settings.metric, mode=settings.mode)``
(``search=ray.tune.search.hyperopt:HyperOptSearch``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from spread.registry import Registry, RegistryError, resolve


@dataclass(frozen=True)
class SearchSpec:
    """A search algorithm (module docstring)."""

    name: str
    build: Callable | None = None
    grid: bool = False
    description: str = ""


@dataclass(frozen=True)
class TrialSchedulerSpec:
    """A trial scheduler (module docstring)."""

    name: str
    build: Callable
    description: str = ""


def _by_target(cls) -> Callable:
    return lambda settings: cls(metric=settings.metric, mode=settings.mode)


def _adapt_search(name: str, obj) -> SearchSpec:
    if isinstance(obj, SearchSpec):
        return obj if obj.name == name else SearchSpec(name, obj.build, obj.grid, obj.description)
    if isinstance(obj, type):
        return SearchSpec(name, _by_target(obj), description=(obj.__doc__ or "").strip().split("\n")[0])
    raise RegistryError(f"searcher entry point '{name}': expected a SearchSpec or a Ray Tune searcher class, got {obj!r}")


def _adapt_scheduler(name: str, obj) -> TrialSchedulerSpec:
    if isinstance(obj, TrialSchedulerSpec):
        return obj if obj.name == name else TrialSchedulerSpec(name, obj.build, obj.description)
    if isinstance(obj, type):
        return TrialSchedulerSpec(name, _by_target(obj), (obj.__doc__ or "").strip().split("\n")[0])
    raise RegistryError(f"trial scheduler entry point '{name}': expected a TrialSchedulerSpec or a Ray Tune "
                        f"scheduler class, got {obj!r}")


SEARCHES: Registry[SearchSpec] = Registry("sweep search", "spread.searchers", adapt=_adapt_search)
TRIAL_SCHEDULERS: Registry[TrialSchedulerSpec] = Registry("trial scheduler", "spread.trial_schedulers",
                                                          adapt=_adapt_scheduler)


def search_spec(name: str) -> SearchSpec:
    """The search ``name``: registered, or a ``"module:Class"`` searcher; else an error naming the registered ones."""
    if ":" in str(name):
        return _adapt_search(str(name), _resolve(name, "search"))
    return SEARCHES.get(str(name))


def trial_scheduler_spec(name: str) -> TrialSchedulerSpec:
    """The trial scheduler ``name``: registered, or a ``"module:Class"`` Ray Tune scheduler."""
    if ":" in str(name):
        return _adapt_scheduler(str(name), _resolve(name, "scheduler"))
    return TRIAL_SCHEDULERS.get(str(name))


def _resolve(target: str, key: str):
    try:
        return resolve(str(target))
    except (ImportError, AttributeError) as exc:
        raise RegistryError(f"{key}={target}: {type(exc).__name__}: {exc}") from exc


def limited(search_alg, max_concurrent: int):
    """``search_alg`` (a Ray Tune searcher or search algorithm, or None: Tune's own variant generation) running at
    most ``max_concurrent`` trials at once, whatever kind it is: a ``Searcher`` in a ``ConcurrencyLimiter``, a
    search algorithm through its own ``set_max_concurrency`` (Tune's ``max_concurrent_trials`` alone is ignored
    for these, with a warning only); ``ValueError`` for one that cannot be limited."""
    from ray.tune.search import BasicVariantGenerator, ConcurrencyLimiter, Searcher

    if search_alg is None:
        return BasicVariantGenerator(max_concurrent=int(max_concurrent))
    if isinstance(search_alg, BasicVariantGenerator):  # random search: its own limit (no Searcher interface)
        search_alg.max_concurrent = int(max_concurrent)
        return search_alg
    if isinstance(search_alg, ConcurrencyLimiter):
        return search_alg
    if isinstance(search_alg, Searcher):
        return ConcurrencyLimiter(search_alg, max_concurrent=int(max_concurrent))
    if search_alg.set_max_concurrency(int(max_concurrent)):
        return search_alg
    raise ValueError(f"{type(search_alg).__name__} cannot limit its trials to max_concurrent={max_concurrent}")


def _random(settings):
    from ray.tune.search import BasicVariantGenerator

    return BasicVariantGenerator(random_state=int(settings.search_seed), max_concurrent=int(settings.max_concurrent))


def _optuna(settings):
    from ray.tune.search.optuna import OptunaSearch

    return OptunaSearch(metric=settings.metric, mode=settings.mode, seed=int(settings.search_seed))


def _asha(settings):
    from ray.tune.schedulers import ASHAScheduler

    return ASHAScheduler(metric=settings.metric, mode=settings.mode, time_attr="training_iteration",
                         **dict(settings.asha or {}))


SEARCHES.register("grid", SearchSpec("grid", None, grid=True, description="every combination once"))
SEARCHES.register("random", SearchSpec("random", _random, description="random draws, seeded by search_seed"))
SEARCHES.register("optuna", SearchSpec("optuna", _optuna, description="Optuna TPE through Ray Tune's OptunaSearch"))
TRIAL_SCHEDULERS.register("asha", TrialSchedulerSpec("asha", _asha, "ASHA: stops the worst trials early"))
