"""Named registries of the platform's extension points, each also filled from Python entry points.

One :class:`Registry` each holds the metrics (:mod:`spread.metrics.registry`), methods
(:mod:`spread.methods.registry`), guidance terms (:mod:`spread.guidance.terms`), dataset importers
(:mod:`spread.importers.registry`) and physics engines (:mod:`spread.physics.engines`). An entry is defined
once, where its code is (a decorator or a ``register`` call in that module), and everything that lists
metrics, methods, terms, importers or engines iterates the registry (DESIGN §8, "Extending").

Entries come from three places, loaded on first use:

1. the modules that define them (a registry knows the packages whose modules register built-ins, and imports
   every module of them, so a new built-in is one new file). A module named among the packages (not a package)
   fixes its entries' place: the built-ins of the named modules come first, in that order, whichever module a
   process happened to import first (the metrics' default selection is part of an evaluation's fingerprint);
2. **entry points** of installed distributions, group ``spread.<kind>`` (``spread.metrics``, ``spread.methods``,
   ``spread.guidance``, ``spread.importers``, ``spread.physics``): the entry point's name is the registered
   name, its object is an entry or what the registry's ``adapt`` turns into one (a ``SceneMetric`` subclass,
   for instance);
3. ``register`` calls at run time (tests, notebooks).

A plugin that fails to load does not take the others with it — whatever it raises on import, ``SystemExit``
included (only ``KeyboardInterrupt`` goes through) — and neither does one refused by the registry's ``check`` (a
metric named like a field of ``metrics.json``) or one whose name a built-in already holds: its name is listed
with the error (:meth:`Registry.failed`), a :class:`PluginWarning` says so on the console, and asking for it
raises that error.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import pkgutil
import warnings
from typing import Callable, Generic, Iterator, TypeVar

T = TypeVar("T")


def resolve(target):
    """The object a ``"package.module:attribute"`` string names (imported now), or ``target`` itself when it is not
    a string; a malformed string is a :class:`RegistryError` naming it."""
    if not isinstance(target, str):
        return target
    module, _, attr = target.partition(":")
    if not module or not attr:
        raise RegistryError(f"{target!r}: expected 'package.module:attribute'")
    return getattr(importlib.import_module(module), attr)


class RegistryError(ValueError):
    """An unknown name, a name registered twice, or a plugin that failed to load."""


class PluginWarning(UserWarning):
    """A plugin (entry point) that was not loaded: the message names it and why; the others are loaded."""


class Registry(Generic[T]):
    """Entries of one kind by name (module docstring).

    kind: what the entries are, for messages ("metric"); group: the entry-point group (``spread.metrics``);
    packages: modules whose submodules define built-in entries (imported on first use); adapt:
    ``adapt(name, obj) → entry`` for what an entry point's object is when it is not an entry yet; check:
    ``check(name, entry, others)`` raising :class:`RegistryError` for an entry that may not be registered (others:
    the entries registered so far, name → entry), run by every :meth:`register`.
    """

    def __init__(self, kind: str, group: str, packages: tuple[str, ...] = (),
                 adapt: Callable[[str, object], T] | None = None,
                 check: Callable[[str, T, dict], None] | None = None):
        self.kind, self.group, self.packages = kind, group, tuple(packages)
        self.adapt, self.check = adapt, check
        self._entries: dict[str, T] = {}
        self._origin: dict[str, str] = {}
        self._failed: dict[str, str] = {}
        self._loaded = False
        self._loading = False

    # ---- filling ----------------------------------------------------------------------------------------
    def register(self, name: str, entry: T, origin: str = "", replace: bool = False) -> T:
        """Add ``entry`` under ``name``; a second entry under one name is an error unless ``replace``."""
        if not isinstance(name, str) or not name or not name.replace("_", "").replace("-", "").replace("+", "").isalnum():
            raise RegistryError(f"{self.kind} name {name!r}: use letters, digits, '_', '-' or '+'")
        if name in self._entries and not replace and self._entries[name] is not entry:
            raise RegistryError(f"{self.kind} '{name}' is registered twice ({self._origin.get(name) or 'built-in'} "
                                f"and {origin or 'built-in'})")
        if self.check is not None:
            self.check(name, entry, {k: v for k, v in self._entries.items() if k != name})
        self._entries[name] = entry
        self._origin[name] = origin
        self._failed.pop(name, None)
        return entry

    def unregister(self, name: str) -> None:
        """Remove ``name`` (tests that register an entry for their own use)."""
        self._entries.pop(name, None)
        self._origin.pop(name, None)

    def load(self) -> None:
        """Import the built-in modules and the entry points of group :attr:`group` (once)."""
        if self._loaded or self._loading:
            return
        self._loading = True
        try:
            for package in self.packages:
                self._import_package(package)
            self._order_named_modules()
            for ep in importlib.metadata.entry_points(group=self.group):
                origin = f"entry point '{ep.name} = {ep.value}' ({ep.dist.name if ep.dist else 'unknown'})"
                if ep.name in self._entries:  # a built-in (or an earlier plugin) keeps its name
                    if self._origin.get(ep.name) == origin:  # the same entry point seen twice
                        continue
                    held = self._origin.get(ep.name) or f"the built-in {self.kind}"
                    self._fail(ep.name, f"{origin} not loaded: the name '{ep.name}' is taken by {held}; rename the "
                                        f"plugin")
                    continue
                try:
                    obj = ep.load()
                    entry = self.adapt(ep.name, obj) if self.adapt is not None else obj
                    self.register(ep.name, entry, origin)
                except KeyboardInterrupt:
                    raise
                except BaseException as exc:  # SystemExit too: one broken plugin never stops the command
                    detail = str(exc) if str(exc) else "(no message)"
                    self._fail(ep.name, f"{origin} failed to load: {type(exc).__name__}: {detail}")
            self._loaded = True
        finally:
            self._loading = False

    def _fail(self, name: str, reason: str) -> None:
        """List plugin ``name`` as failed with ``reason`` and say so once on the console."""
        if name not in self._failed:
            warnings.warn(f"{self.kind} plugin '{name}': {reason}", PluginWarning, stacklevel=3)
        self._failed.setdefault(name, reason)

    def _order_named_modules(self) -> None:
        """Entries defined in a module named in :attr:`packages` first, in that order (their ``origin`` is
        ``module.object``); every other entry after them, in registration order."""
        named = [p for p in self.packages if not hasattr(importlib.import_module(p), "__path__")]
        if not named:
            return

        def rank(name: str) -> int:
            origin = self._origin.get(name, "")
            return next((i for i, module in enumerate(named) if origin.startswith(f"{module}.")), len(named))

        order = sorted(self._entries, key=rank)  # stable: the rest keep their registration order
        self._entries = {name: self._entries[name] for name in order}

    @staticmethod
    def _import_package(package: str) -> None:
        module = importlib.import_module(package)
        for info in pkgutil.iter_modules(getattr(module, "__path__", []), prefix=f"{package}."):
            importlib.import_module(info.name)

    # ---- reading ----------------------------------------------------------------------------------------
    def get(self, name: str) -> T:
        """The entry of ``name``; an unknown name is an error listing the known ones."""
        self.load()
        if name in self._entries:
            return self._entries[name]
        if name in self._failed:
            raise RegistryError(f"{self.kind} '{name}': {self._failed[name]}")
        raise RegistryError(f"unknown {self.kind} '{name}' (known: {', '.join(self.names()) or 'none'}; plugins "
                            f"register under the entry-point group '{self.group}')")

    def names(self) -> list[str]:
        """Registered names, built-ins in registration order, then plugins."""
        self.load()
        return list(self._entries)

    def items(self) -> Iterator[tuple[str, T]]:
        self.load()
        return iter(list(self._entries.items()))

    def origin(self, name: str) -> str:
        """Where ``name`` came from: "" for a built-in, else the entry point or caller that registered it."""
        self.load()
        return self._origin.get(name, "")

    def failed(self) -> dict[str, str]:
        """Entry points that failed to load: name → reason."""
        self.load()
        return dict(self._failed)

    def __contains__(self, name: str) -> bool:
        self.load()
        return name in self._entries
