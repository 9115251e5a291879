"""The household category catalog: what can be built, with the metadata procgen queries.

``CATALOG[name]`` is a :class:`~spread.assets.categories.registry.CategoryInfo` (role, density,
tags, styles, generator). :func:`make_spec` turns (category, variant, seed) into an
:class:`~spread.assets.assemble.AssetSpec`, deterministically: variant ``v`` of category ``c`` draws
from a numpy Generator seeded with ``(seed, sha256(c), v)``, independent of Python's hash seed,
of the process and of the other categories.
"""

from __future__ import annotations

import hashlib

import numpy as np

# Importing the generator modules registers their categories.
from spread.assets.categories import (  # noqa: F401
    containers, decor, electronics, kitchenware, misc, seating, storage, tables,
)
from spread.assets.categories.registry import REGISTRY, CategoryInfo
from spread.assets.assemble import AssetSpec

#: category name → CategoryInfo, for every registered category.
CATALOG: dict[str, CategoryInfo] = REGISTRY


def default_categories() -> list[str]:
    """Every catalog category, sorted."""
    return sorted(CATALOG)


def furniture_categories() -> list[str]:
    """Categories that stand on the floor (role "furniture")."""
    return sorted(c for c, info in CATALOG.items() if info.role == "furniture")


def object_categories() -> list[str]:
    """Categories placed on support surfaces (role "object")."""
    return sorted(c for c, info in CATALOG.items() if info.role == "object")


def categories_with_tag(tag: str) -> list[str]:
    """Categories carrying ``tag`` (e.g. "stackable", "container", "kitchen")."""
    return sorted(c for c, info in CATALOG.items() if tag in info.tags)


def asset_id(category: str, variant: int) -> str:
    """The library id of a variant, e.g. ``mug_03``."""
    return f"{category}_{variant:02d}"


def variant_rng(seed: int, category: str, variant: int) -> np.random.Generator:
    """The Generator that draws variant ``variant`` of ``category`` under ``seed``."""
    key = int.from_bytes(hashlib.sha256(category.encode()).digest()[:8], "little")
    return np.random.default_rng([int(seed), key, int(variant)])


def make_spec(category: str, variant: int, seed: int = 0) -> AssetSpec:
    """Generate variant ``variant`` of ``category`` as a spec (no files written)."""
    try:
        info = CATALOG[category]
    except KeyError:
        raise KeyError(f"unknown asset category '{category}' (known: {', '.join(default_categories())})") from None
    shape = info.shape(variant_rng(seed, category, variant), variant)
    tags = list(dict.fromkeys([*info.tags, *shape.tags]))
    return AssetSpec(
        asset_id=asset_id(category, variant), category=category, variant=variant, role=info.role,
        parts=shape.parts, density=info.density, rest_poses=dict(shape.rest_poses),
        rest_weights=dict(shape.rest_weights), support_surfaces=list(shape.surfaces), tags=tags,
    )
