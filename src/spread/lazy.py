"""A package's public names imported on first access (PEP 562), so that importing one light module of a package
(``spread.model.config``, ``spread.metrics.constants``) does not import the heavy ones beside it.

``__getattr__, __dir__ = lazy_names(__name__, {"spread.model.config": ("ModelConfig",), ...})`` in the
package's ``__init__``: every name, and the module that defines it."""

from __future__ import annotations

import importlib
import importlib.util
from typing import Callable, Mapping, Sequence


def lazy_names(package: str, exports: Mapping[str, Sequence[str]]) -> tuple[Callable, Callable]:
    """The ``__getattr__`` and ``__dir__`` of ``package``: a name of ``exports`` (module → names) is imported from
    its module when first asked for, then kept in the package (asked once); a submodule's name imports it (as an
    eager ``__init__`` had); any other name is an AttributeError."""
    module_of = {name: module for module, names in exports.items() for name in names}
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str):
        module = module_of.get(name)
        if module is None:  # a submodule asked for as an attribute (``spread.metrics.base``) is imported too
            if not name.startswith("_") and importlib.util.find_spec(f"{package}.{name}") is not None:
                return importlib.import_module(f"{package}.{name}")
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        namespace[name] = value
        return value

    def __dir__() -> list[str]:
        return sorted({*namespace, *module_of})

    return __getattr__, __dir__
