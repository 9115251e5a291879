"""Asset library: procedural household meshes built from convex parts, with per-asset caches."""
from spread.assets.library import AssetLibrary, AssetRecord, RestPose, SupportSurface, AssetError  # noqa: F401
