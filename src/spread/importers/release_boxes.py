"""The SPREAD release's ``boxes.npz`` (L-avenir/SPREAD) → a :class:`~spread.scene.Scene`: the format converter
the ``spread_release`` importer uses (moved here from ``spread.scene``, which keeps only the platform's own file
format). Frames and units: DESIGN §3; what the release's keys mean: docs/real_data.md.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

from spread.scene import NUM_PHYSICAL, SPATIAL_SELF, Scene, _fail, load_npz_arrays, validate_scene


def read_reference_boxes(path: str | os.PathLike, scene_id: str | None = None,
                         meshes: Mapping[str, "object"] | None = None) -> Scene:
    """Convert the reference release's ``boxes.npz`` into a Scene.

    The release places a mesh by ``v_world = R · (v_local − bbox_center) + T``: its local meshes are
    not bbox-centred, ``T_bbox`` is the world bbox centre and ``bbox_center`` the local one. Our
    canonical mesh is the release mesh shifted by ``−bbox_center``, so ``translation = T_bbox`` and
    ``rotation = R_bbox`` carry over unchanged. Index 0 is a placeholder and is dropped; ``relations``
    triples ``[s, p, o]`` (indices into the N+1 arrays, p: 0 empty, 1 support, 2 contact) become the
    dense directed ``physical`` matrix; ``regions_bbox`` (N+1, N+1) becomes ``spatial``.
    ``bbox_center`` and, when present, ``miche_feature``/``xyz``/``normal`` are kept as extras
    (``reference_bbox_center``, ``shape_tokens``, ``surface_points``, ``surface_normals``).
    Categories are the asset id with trailing ``_<digits>`` and ``_unpacked`` parts removed.

    The file is read with ``allow_pickle=False`` (:func:`load_npz_arrays`): a key stored as an object
    array (pickled Python objects, which could run code when loaded) is refused with an error naming it.
    """
    path = Path(path)
    src = str(path)
    arrays = load_npz_arrays(path)
    return reference_scene(arrays, src, scene_id or path.parent.name or path.stem, meshes)


def reference_scene(arrays: Mapping[str, np.ndarray], src: str, scene_id: str,
                    meshes: Mapping[str, "object"] | None = None) -> Scene:
    """The Scene of the release's ``boxes.npz`` arrays (see :func:`read_reference_boxes`); errors name
    ``src`` and the release's key."""
    for key in ("T_bbox", "R_bbox", "obj_names", "regions_bbox"):
        if key not in arrays:
            _fail(src, key, "missing required key of the reference boxes.npz layout")
    T = np.asarray(arrays["T_bbox"], dtype=np.float64)
    R = np.asarray(arrays["R_bbox"], dtype=np.float64)
    names = np.asarray(arrays["obj_names"]).astype(str)
    n1 = names.shape[0]
    if n1 < 2:
        _fail(src, "obj_names", f"{n1} entries: needs the placeholder at index 0 and at least one object")
    for key, arr, shape in (("T_bbox", T, (n1, 3)), ("R_bbox", R, (n1, 3, 3))):
        if arr.shape != shape:
            _fail(src, key, f"shape {arr.shape}, expected {shape} (N+1 = {n1} from obj_names)")
    for key, arr in (("T_bbox", T), ("R_bbox", R)):
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = np.argwhere(bad)[0].tolist()
            _fail(src, key, f"non-finite value {arr[tuple(idx)]} at index {idx}")
    regions = np.asarray(arrays["regions_bbox"])
    if regions.shape != (n1, n1):
        _fail(src, "regions_bbox", f"shape {regions.shape}, expected {(n1, n1)}")
    integral = regions.dtype.kind in "iu" or (regions.dtype.kind == "f" and np.isfinite(regions).all()
                                               and (regions == np.round(regions)).all())
    if not integral or ((regions[1:, 1:] < 0) | (regions[1:, 1:] > SPATIAL_SELF)).any():
        _fail(src, "regions_bbox", f"codes must be integers in 0..{SPATIAL_SELF} (dtype {regions.dtype})")
    for key in ("bbox_center", "miche_feature", "xyz", "normal"):
        if key in arrays and (arrays[key].ndim < 1 or arrays[key].shape[0] != n1):
            _fail(src, key, f"shape {arrays[key].shape}: first axis must be N+1 = {n1} (from obj_names)")
        if key in arrays and arrays[key].dtype.kind not in "fiu":
            _fail(src, key, f"expected numbers, got dtype {arrays[key].dtype}")
    if "relations" in arrays and arrays["relations"].size and (
            arrays["relations"].dtype.kind not in "iuf" or arrays["relations"].size % 3
            or not np.all(np.asarray(arrays["relations"]) == np.round(np.asarray(arrays["relations"], float)))):
        _fail(src, "relations", f"expected integer triples [s, p, o], got shape {arrays['relations'].shape} "
                                f"dtype {arrays['relations'].dtype}")
    n = n1 - 1
    physical = np.zeros((n, n), dtype=np.int8)
    relations = np.asarray(arrays.get("relations", np.zeros((0, 3), int)))
    if relations.size:
        relations = relations.reshape(-1, 3).astype(np.int64)
        for s, p, o in relations:
            if not (0 <= s < n1 and 0 <= o < n1):
                _fail(src, "relations", f"triple {[int(s), int(p), int(o)]} indexes outside 0..{n1 - 1}")
            if not (0 <= p < NUM_PHYSICAL):
                _fail(src, "relations", f"triple {[int(s), int(p), int(o)]} has predicate {p} out of 0..2")
            if s == 0 or o == 0 or s == o:
                continue  # the placeholder root and self loops carry no object relation
            physical[s - 1, o - 1] = p
    spatial = regions[1:, 1:].astype(np.int8)
    np.fill_diagonal(spatial, SPATIAL_SELF)
    extras: dict[str, np.ndarray] = {}
    if "bbox_center" in arrays:
        extras["reference_bbox_center"] = np.asarray(arrays["bbox_center"], np.float32)[1:]
    for ref_key, our_key in (("miche_feature", "shape_tokens"), ("xyz", "surface_points"), ("normal", "surface_normals")):
        if ref_key in arrays:
            extras[our_key] = np.asarray(arrays[ref_key], np.float32)[1:]
    object_names = names[1:]
    categories = np.array([_reference_category(nm) for nm in object_names])
    scene = Scene(
        scene_id=scene_id,
        asset_id=object_names, category=categories,
        translation=T[1:], rotation=R[1:], spatial=spatial, physical=physical,
        extras=extras,
    )
    validate_scene(scene, source=src, assets=meshes.keys() if meshes is not None else None)
    return scene


def _reference_category(asset_name: str) -> str:
    parts = [p for p in asset_name.replace("_unpacked", "").split("_") if p]
    while len(parts) > 1 and parts[-1].isdigit():
        parts.pop()
    return "_".join(parts).lower() if parts else asset_name.lower()
