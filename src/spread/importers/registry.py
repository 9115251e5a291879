"""The importer registry: each source layout defined once (``spread-import source=<name>``).

An importer is a factory ``factory(cfg) → Source`` (:class:`~spread.importers.base.Source`, given the
:class:`~spread.importers.run.ImportConfig`) registered under its name in its own module (``spread_release``,
``threed_front``); the import driver (rooms in parallel, assets, resume, manifest) is the same for all. Another
package adds a layout through the entry-point group ``spread.importers`` naming such a factory (or a ``Source``
subclass, built as ``cls(cfg)``).
"""

from __future__ import annotations

from typing import Callable

from spread.registry import Registry

IMPORTERS: Registry[Callable] = Registry("importer", "spread.importers", packages=("spread.importers",))


def register_importer(name: str, factory: Callable) -> Callable:
    """Register ``factory(cfg) → Source`` as ``source=<name>``."""
    return IMPORTERS.register(name, factory, origin=getattr(factory, "__module__", ""))


def importer_names() -> list[str]:
    return IMPORTERS.names()
