"""Asset library: procedural household meshes built from convex parts, with per-asset caches.

Modules: ``library`` (records, on-disk library, caches), ``assemble`` (convex parts → mesh, frame, record on disk), ``catalog``
(categories, roles, densities, tags; ``make_spec``), ``build`` (``build_library``: every category ×
variant, deterministic, resumable, parallel), ``categories/*`` (the generators), ``primitives``
(convex building blocks), ``stability`` (rest-pose checks), ``queries`` (fits-on-surface questions),
``physics`` (assets as pybullet compounds). Import the heavy ones (catalog, build, physics)
explicitly: this package import stays light.
"""
from spread.assets.library import AssetLibrary, AssetRecord, RestPose, SupportSurface, AssetError  # noqa: F401
