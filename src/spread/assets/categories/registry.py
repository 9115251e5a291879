"""The category registry: each generator module registers its categories with :func:`category`.

A generator is ``generate(rng, style) -> Shape``: ``rng`` (numpy Generator) draws the variant's
dimensions and small choices, ``style`` is one of the category's ``styles``; variant ``v`` uses
``styles[v % len(styles)]`` so that any five consecutive variants cover up to five styles.
Everything is in metres in the generator's build frame (see :mod:`spread.assets.shape`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from spread.assets.shape import Shape

Generator = Callable[[np.random.Generator, str], Shape]


@dataclass(frozen=True)
class CategoryInfo:
    """Metadata of one category.

    ``role`` is "furniture" (stands on the floor) or "object" (placed on support surfaces);
    ``density`` (kg/m³) is the *effective* density of the modelled solid (mass = mesh volume ×
    density): upholstered furniture and closed cabinets are mostly air, hollow ceramics are modelled
    with true walls. ``tags``: "stackable" (copies stack), "container" (holds objects inside), plus
    room/use hints such as "kitchen", "tableware", "office", "decor", "electronics", "soft".
    ``styles`` names the shape styles that variants cycle through.
    """

    name: str
    role: str
    density: float
    generate: Generator
    tags: tuple[str, ...] = ()
    styles: tuple[str, ...] = ("default",)
    description: str = ""

    def style(self, index: int) -> str:
        """The style variant ``index`` uses."""
        return self.styles[index % len(self.styles)]

    def shape(self, rng: np.random.Generator, index: int) -> Shape:
        """Variant ``index`` drawn with ``rng``."""
        return self.generate(rng, self.style(index))


#: name → CategoryInfo, filled as the generator modules are imported (see spread.assets.catalog).
REGISTRY: dict[str, CategoryInfo] = {}


def category(name: str, role: str, density: float, tags: tuple[str, ...] = (),
             styles: tuple[str, ...] = ("default",), description: str = ""):
    """Decorator registering ``generate(rng, style) -> Shape`` as category ``name``."""
    if role not in ("furniture", "object"):
        raise ValueError(f"category '{name}': role must be 'furniture' or 'object', not {role!r}")

    def register(generate: Generator) -> Generator:
        if name in REGISTRY:
            raise ValueError(f"category '{name}' is registered twice")
        REGISTRY[name] = CategoryInfo(name, role, float(density), generate, tuple(tags), tuple(styles),
                                      description or (generate.__doc__ or "").strip().split("\n")[0])
        return generate

    return register
