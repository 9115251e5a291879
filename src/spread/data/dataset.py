"""``SceneDataset``: one dataset split's scene files as model-ready tensors.

Dataset folder (DESIGN §4): ``<root>/<split>/*.npz`` scene files, ``<root>/assets`` the asset
library, ``<root>/stats.json`` the normalisation bounds, ``<root>/manifest.json`` (optional here)
whose ``categories`` list fixes the category indices. Each item is one scene of N objects:

============== ============== =====================================================================
key            shape, dtype   meaning
============== ============== =====================================================================
x              (N, 9) float32 [normalised world translation (3, in [−1, 1]), rot6d of R (6)]
spatial        (N, N) int64   spatial codes 0..6 (row i "is … of" column j)
physical       (N, N) int64   physical codes 0 none, 1 i supports j, 2 contact
asset_index    (N,) int64     index into ``asset_ids`` (the library's sorted asset ids)
shape_index    (N,) int64     which point set the object carries: ``asset_index``, + len(asset_ids) when
                              mirrored (:meth:`SceneDataset.item`); equal indices, equal points
category_index (N,) int64     index into ``categories``
points         (N, M, 3) f32  surface samples, canonical (object-local, bbox-centred) frame, metres
normals        (N, M, 3) f32  their unit normals, same frame
extents        (N, 3) f32     each asset's canonical bbox size (the library record's ``extents``), metres
room           (2, 3) f32     the scene's floor/room bounds [min, max] (metres); NaN when the file has none
scene_id       str
part_planes    (N, P, F, 4)   with ``geometry_distance='parts'`` only: each asset's convex part planes [n, d]
                              (canonical frame, :mod:`spread.data.parts`); ``part_boxes`` (N, P, 2, 3) their
                              boxes, ``part_valid`` (N, P) bool
============== ============== =====================================================================

``extents`` and ``room`` serve models that reason about boxes and the floor (the baselines of
:mod:`spread.methods`); SceneDiffusion does not read them.

Scene files are validated on read (against the library too), so a broken file fails with an error
naming the file and key. ``bounds`` (6 floats) replaces stats.json's translation bounds in the normalisation
(the square bounds of an augmented training run, :mod:`spread.data.augment`); :meth:`SceneDataset.item`
encodes a scene after one of the 8 floor symmetries (poses, spatial codes and, when mirrored, the points and part
planes). The dataset pickles without its library (it holds a lock and meshes); a worker process that gets a
pickled copy reloads the library lazily from its folder.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from spread.data.points import DEFAULT_NUM_POINTS, asset_points
from spread.data.rotation import matrix_to_rot6d
from spread.data.stats import load_stats, normalize_translation, translation_bounds
from spread.io import read_json
from spread.scene import Scene, list_scene_files, read_scene, scene_mounts


def load_manifest_categories(path: Path) -> list[str] | None:
    """The ``categories`` list of ``manifest.json``, or None when the file or key is absent."""
    if not path.exists():
        return None
    manifest = read_json(path)  # a file that is not JSON, or not a regular file, is a ValueError naming it
    cats = manifest.get("categories") if isinstance(manifest, dict) else None
    if cats is None:
        return None
    if not isinstance(cats, list) or not all(isinstance(c, str) for c in cats) or len(set(cats)) != len(cats):
        raise ValueError(f"{path}: key 'categories' must be a list of distinct strings")
    return list(cats)


def screen_scene_files(files: list[Path], library, reader=None, used: dict[str, str] | None = None,
                       max_objects: int | None = None, span: dict | None = None) -> tuple[list[Path], list[dict]]:
    """(the files that read back as valid, plausible scenes of ``library``; one ``{"file", "error"}`` per
    other one): a damaged, hostile or absurd file is skipped, counted and named in a warning instead of
    stopping a run mid-epoch (every file is read once here; reading is a few ms per scene). ``reader(path,
    library)``: how a file is read (default :func:`~spread.scene.read_scene`); ``used``: filled with each category
    the good files use → the first file using it; ``max_objects``: a scene of more objects is skipped and named too
    (``data.max_objects``: a room too large to train on fails its batch on memory, mid-epoch, otherwise); ``span``:
    filled with the good files' translation extremes per axis (``lo``, ``hi``: metres) and the files holding them
    (``lo_file``, ``hi_file``)."""
    good, skipped = [], []
    for path in files:
        try:
            scene = (reader or read_scene)(path, library)
        except Exception as exc:  # SceneFormatError names file and key; anything else still names the file
            message = str(exc) if str(path) in str(exc) else f"{path}: {type(exc).__name__}: {exc}"
            skipped.append({"file": str(path), "error": message})
        else:
            if max_objects is not None and int(scene.num_objects) > int(max_objects):
                skipped.append({"file": str(path), "error": f"{path}: {int(scene.num_objects)} objects, more than the "
                                                           f"object limit {int(max_objects)} (data.max_objects)"})
                continue
            good.append(path)
            if span is not None and len(getattr(scene, "translation", ())):
                note_span(span, np.asarray(scene.translation, np.float64), path)
            if used is not None:
                for category in getattr(scene, "category", ()):
                    used.setdefault(str(category), str(path))
    if skipped:
        import logging

        logging.getLogger("spread.data").warning(
            "skipped %d of %d scene files in %s: %s", len(skipped), len(files), Path(files[0]).parent,
            "; ".join(s["error"] for s in skipped[:3]) + (" …" if len(skipped) > 3 else ""))
    return good, skipped


def check_max_objects(value) -> int | None:
    """``data.max_objects``: None (no limit) or a whole number ≥ 1, else a ValueError naming the value."""
    from spread.checks import whole_number

    return whole_number(value, "data.max_objects", 1, null="no limit")


def note_span(span: dict, translation: np.ndarray, path: Path) -> None:
    """Widen ``span`` (:func:`screen_scene_files`) by one scene's (N, 3) translations."""
    lo, hi = translation.min(axis=0), translation.max(axis=0)
    if "lo" not in span:
        span.update(lo=lo, hi=hi, lo_file=[str(path)] * 3, hi_file=[str(path)] * 3)
        return
    for axis in range(3):
        if lo[axis] < span["lo"][axis]:
            span["lo"][axis], span["lo_file"][axis] = lo[axis], str(path)
        if hi[axis] > span["hi"][axis]:
            span["hi"][axis], span["hi_file"][axis] = hi[axis], str(path)


def bounds_problem(stats_path: Path, stats: dict, span: dict, tolerance: float = 1e-4) -> str | None:
    """Why ``stats.json``'s ``bounds_translations`` do not hold the training rooms' translations (``span``), or None:
    a translation outside them is clipped to them when normalised, so a hand-edited bound trains on other poses than
    the rooms'. The statistics are computed from the training rooms, so theirs always fit (``tolerance``: metres)."""
    if "lo" not in span:
        return None
    lo, hi = translation_bounds(stats, source=str(stats_path))
    for axis, name in enumerate("xyz"):
        if span["lo"][axis] < lo[axis] - tolerance:
            where, value, bound = span["lo_file"][axis], span["lo"][axis], f"min {lo[axis]:g}"
        elif span["hi"][axis] > hi[axis] + tolerance:
            where, value, bound = span["hi_file"][axis], span["hi"][axis], f"max {hi[axis]:g}"
        else:
            continue
        return (f"{stats_path}: key 'bounds_translations' does not hold the training rooms ({name} = {value:.4g} m in "
                f"{where}, outside its {bound}): their translations are clipped to it; write the statistics anew from "
                f"the training rooms (spread.data.compute_stats) or restore the file")
    return None


class SceneDataset(torch.utils.data.Dataset):
    """Scenes of ``<root>/<split>`` encoded as tensors (see the module docstring for the keys)."""

    def __init__(self, root: str | os.PathLike, split: str, library=None,
                 num_points: int = DEFAULT_NUM_POINTS, seed: int = 0, bounds: list[float] | None = None,
                 cache: bool = False, reader=None, geometry_distance: str = "chamfer",
                 max_objects: int | None = None):
        from spread.assets.library import AssetLibrary
        from spread.data.parts import READS_PARTS, check_geometry_distance

        self.root = Path(root)
        self.split = split
        self.num_points = int(num_points)
        self.seed = int(seed)
        # the model's distance decides whether the batch carries convex part planes (data/parts.py)
        self.parts = check_geometry_distance(geometry_distance, "data.geometry_distance") in READS_PARTS
        if self.num_points < 1:
            raise ValueError(f"num_points must be ≥ 1, got {num_points}")
        self.files = list_scene_files(self.root / split)
        if not self.files:
            raise FileNotFoundError(f"{self.root / split}: no scene files (*.npz)")
        self.stats = load_stats(self.root / "stats.json")
        if bounds is not None:
            self.stats = {**self.stats, "bounds_translations": [float(b) for b in bounds]}
            translation_bounds(self.stats, source=f"{self.root}: bounds")
        self._library = library if library is not None else AssetLibrary.load(self.root / "assets")
        self._library_root = Path(self._library.root)
        self.reader = reader  # (path, library) → Scene; None: read_scene (spread.readonce.scene: once per process)
        used: dict[str, str] = {}
        self.max_objects = check_max_objects(max_objects)
        span: dict = {}
        self.files, self.skipped = screen_scene_files(self.files, self._library, reader, used, self.max_objects, span)
        if split == "train" and bounds is None:  # the bounds were computed from these rooms
            problem = bounds_problem(self.root / "stats.json", self.stats, span)
            if problem:
                import logging

                logging.getLogger("spread.data").warning(problem)
        if not self.files:
            raise ValueError(f"{self.root / split}: none of its {len(self.skipped)} scene files is usable "
                             f"(first: {self.skipped[0]['error']})")
        self.asset_ids: list[str] = sorted(self._library.records)
        self.categories: list[str] = (load_manifest_categories(self.root / "manifest.json")
                                      or list(self._library.categories))
        unlisted = sorted(set(used) - set(self.categories))
        if unlisted:  # the manifest is the bad file: said now, not when the first such scene is encoded mid-epoch
            shown = ", ".join(map(repr, unlisted[:4])) + (" …" if len(unlisted) > 4 else "")
            raise ValueError(f"{self.root / 'manifest.json'}: key 'categories' lacks {shown}, used by "
                             f"{used[unlisted[0]]} (and perhaps others)")
        self._asset_index = {a: i for i, a in enumerate(self.asset_ids)}
        self._category_index = {c: i for i, c in enumerate(self.categories)}
        self._points: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._parts: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self.cache = bool(cache)  # keep every validated Scene record read (a few kB each) in memory
        self._scenes: dict[int, Scene] = {}

    # ---- pickling: drop the library and the point memo, reload lazily ---------------------------
    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_library"] = None
        state["_points"] = {}
        state["_parts"] = {}
        state["_scenes"] = {}
        return state

    @property
    def library(self):
        if self._library is None:
            from spread.assets.library import AssetLibrary

            self._library = AssetLibrary.load(self._library_root)
        return self._library

    # ---- items ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.files)

    def read(self, index: int) -> Scene:
        """The validated Scene record of item ``index`` (kept in memory with ``cache``; callers do not modify it)."""
        scene = self._scenes.get(index)
        if scene is None:
            scene = (self.reader or read_scene)(self.files[index], self.library)
            if self.cache:
                self._scenes[index] = scene
        return scene

    def sizes(self) -> list[int]:
        """The object count of every item (its scene record read once; kept with ``cache``)."""
        if getattr(self, "_sizes", None) is None:
            self._sizes = [int(self.read(i).num_objects) for i in range(len(self))]
        return list(self._sizes)

    def __getitem__(self, index: int) -> dict:
        return self.encode(self.read(index), source=str(self.files[index]))

    def item(self, index: int, transform: int = 0) -> dict:
        """Item ``index`` after floor symmetry ``transform`` ∈ 0..7 (:mod:`spread.data.augment`) about the xz
        centre of the normalisation bounds; 0 is ``self[index]``."""
        from spread.data.augment import bounds_centre, transform_scene

        if transform == 0:
            return self[index]
        centre = bounds_centre(self.stats["bounds_translations"])
        scene = transform_scene(self.read(index), transform, centre)
        return self.encode(scene, source=str(self.files[index]), transform=transform)

    def points_of(self, asset_id: str) -> tuple[np.ndarray, np.ndarray]:
        """(M, 3) points and normals of an asset, memoised; see :mod:`spread.data.points`."""
        hit = self._points.get(asset_id)
        if hit is None:
            hit = asset_points(self.library, asset_id, self.num_points, self.seed)
            self._points[asset_id] = hit
        return hit

    def parts_of(self, asset_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(planes, boxes, valid) of an asset's convex parts, memoised; see :mod:`spread.data.parts`."""
        hit = self._parts.get(asset_id)
        if hit is None:
            from spread.data.parts import asset_part_planes

            hit = asset_part_planes(self.library.convex_parts(asset_id), source=f"asset '{asset_id}'")
            self._parts[asset_id] = hit
        return hit

    def encode(self, scene: Scene, source: str | None = None, transform: int = 0) -> dict:
        """Tensors of one Scene (also used to encode test graphs at sampling time). ``transform``: the floor
        symmetry the scene went through (its points and normals are mirrored when it is a mirror)."""
        source = source or f"scene '{scene.scene_id}'"
        for i, aid in enumerate(scene.asset_id):
            if aid not in self._asset_index:
                raise ValueError(f"{source}: key 'asset_id': object {i} asset '{aid}' is not in the library")
        for i, cat in enumerate(scene.category):
            if cat not in self._category_index:
                raise ValueError(f"{source}: key 'category': object {i} category '{cat}' is not in the "
                                 f"dataset's category list ({len(self.categories)} categories)")
        asset_index = torch.tensor([self._asset_index[a] for a in scene.asset_id], dtype=torch.long)
        t = normalize_translation(scene.translation.astype(np.float32), self.stats)
        x = np.concatenate([t, matrix_to_rot6d(scene.rotation.astype(np.float32))], axis=-1)
        pts, nrm = zip(*(self.points_of(str(a)) for a in scene.asset_id))
        pts, nrm = np.stack(pts), np.stack(nrm)
        if transform >= 4:
            from spread.data.augment import mirror_local

            pts, nrm = mirror_local(pts, transform), mirror_local(nrm, transform)
        item = {
            "x": torch.from_numpy(np.ascontiguousarray(x, np.float32)),
            "spatial": torch.from_numpy(scene.spatial.astype(np.int64)),
            "physical": torch.from_numpy(scene.physical.astype(np.int64)),
            "mount": torch.from_numpy(scene_mounts(scene).astype(np.int64)),
            "asset_index": asset_index,
            "shape_index": asset_index + (len(self.asset_ids) if transform >= 4 else 0),
            "category_index": torch.tensor([self._category_index[c] for c in scene.category], dtype=torch.long),
            "points": torch.from_numpy(np.ascontiguousarray(pts)),
            "normals": torch.from_numpy(np.ascontiguousarray(nrm)),
            "extents": torch.from_numpy(np.stack([np.asarray(self.library[str(a)].extents, np.float32)
                                                  for a in scene.asset_id])),
            "room": torch.from_numpy(np.full((2, 3), np.nan, np.float32) if scene.room is None
                                     else np.asarray(scene.room, np.float32)),
            "scene_id": scene.scene_id,
        }
        if self.parts:
            planes, boxes, valid = zip(*(self.parts_of(str(a)) for a in scene.asset_id))
            planes, boxes = np.stack(planes), np.stack(boxes)
            if transform >= 4:
                from spread.data.parts import mirror_planes

                planes, boxes = mirror_planes(planes, boxes)
            item.update(part_planes=torch.from_numpy(planes), part_boxes=torch.from_numpy(boxes),
                        part_valid=torch.from_numpy(np.stack(valid)))
        return item
