"""``source=spread_release``: the layout the SPREAD authors publish their processed ProcTHOR data in.

Layout of ``src`` (reference_implementation.md §1)::

    train_test_split.json        {"train": [tag, ...], "val": [...], optionally "test": [...]}
    <tag>/boxes.npz              one room: index 0 is a placeholder (dropped)
    meshes/<name>_unpacked.glb   one mesh per ``obj_names`` entry (``<name>.glb`` is accepted too)
    dataset_stats.txt            JSON: ``bounds_translations`` etc. (optional)

``boxes.npz`` keys used: ``T_bbox`` (N+1, 3) world bbox centres, ``R_bbox`` (N+1, 3, 3) world-from-local,
``bbox_center`` (N+1, 3) the local bbox centre, ``obj_names`` (N+1,), ``relations`` (K, 3) triples
``[s, p, o]`` (p: 0 empty, 1 support, 2 contact), ``regions_bbox`` (N+1, N+1) spatial codes (our
vocabulary), optional ``miche_feature``, ``xyz``, ``normal`` (kept as extras ``shape_tokens``,
``surface_points``, ``surface_normals``, in the release's object frame). Read with ``allow_pickle=False``.

Frames. The release places a mesh by ``v_world = R · (v_file − bbox_center) + T``. The library's
canonical mesh is the file's mesh minus its own bbox centre ``c`` (``AssetRecord.source
["canonical_offset"]``), so ``translation = T + R · (c − bbox_center)`` and ``rotation = R``; when the
file's ``bbox_center`` is the mesh's bbox centre (as the release intends) the translation is ``T_bbox``.
The manifest counts objects whose ``bbox_center`` differs from the mesh's by more than 1 mm.

Categories come from a table of the release's asset names, and near-rotations, off-diagonal "self" codes and
support cycles are repaired and counted rather than refused (:mod:`spread.importers.release_details`); the
file's triples, "Empty" and root ones included, stay in the scene as ``release_relations``, and its
``regions_bbox`` as it is (root row and column included) as ``release_regions`` (the release network reads them).

Mounts: from the file's support triples (the root entry's included) and the posed meshes
(:func:`spread.importers.mounts.release_mounts`; counts ``mount_*`` in the manifest).

Splits. ``train`` and ``val`` are the file's lists. When there is no ``test`` list the authors' held-out
list — their ``val``, whose tags read ``ProcTHOR-Test-…`` — is the **test** split, and **val** is carved
from ``train``: the ``max(1, round(val_fraction · n))`` tags with the smallest SHA-256 (independent of
order; training needs a val split). A tag
listed in two splits is kept in the later of test, val, train only (no leakage); both rules and the
counts go to the manifest.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from spread.importers.base import (AssetRequest, RoomList, RoomRef, Source, carve_val, check_tag, error_record,
                                   within)
from spread.io import read_json_object, safe_name
from spread.importers.release_boxes import reference_scene
from spread.scene import SceneFormatError, load_npz_arrays
from spread.importers.registry import register_importer

SPLIT_FILE = "train_test_split.json"
#: Objects whose ``bbox_center`` and mesh bbox centre differ by more than this (metres) are counted.
CENTRE_TOLERANCE = 1e-3


class SpreadRelease(Source):
    """The release layout (module docstring). ``room_type``: a label stored in every scene (the release
    has none of its own); ``val_fraction``: share of train carved into val when the file has no test list."""

    name = "spread_release"
    #: regions_bbox is the file's own graph: its reading is measured on import (spread.importers.conventions)
    spatial_from_file = True
    relations_rule = ("spatial: the file's regions_bbox, in the reading the posed meshes support "
                      "(manifest relations_convention); physical: the file's relations")

    def __init__(self, src: str | Path, room_type: str | None = None, val_fraction: float = 0.05):
        self.src = Path(src)
        self.room_type = room_type
        self.val_fraction = float(val_fraction)
        if not self.src.is_dir():
            raise FileNotFoundError(f"src={self.src}: not a folder")

    def info(self) -> dict:
        return {"source": self.name, "src": str(self.src), "room_type": self.room_type,
                "val_fraction": self.val_fraction,
                "graph": "the file's: relations (physical), regions_bbox (spatial)"}

    # ---- rooms ---------------------------------------------------------------------------------
    def rooms(self) -> RoomList:
        path = self.src / SPLIT_FILE
        if not path.is_file():
            raise FileNotFoundError(f"{path}: split file missing (the release layout lists its tags per split "
                                    f"in {SPLIT_FILE}: {{\"train\": [...], \"val\": [...]}})")
        data = read_json_object(path)
        unknown = sorted(set(data) - {"train", "val", "test"})
        lists = {}
        for key in ("train", "val", "test"):
            if key in data:
                if not isinstance(data[key], list):
                    raise ValueError(f"{path}: key '{key}' must be a list of tags, got {type(data[key]).__name__}")
                lists[key] = data[key]
        if "train" not in lists:
            raise ValueError(f"{path}: key 'train' missing")
        errors, good = [], {}
        for key, tags in lists.items():
            ok = []
            for k, tag in enumerate(tags):
                try:
                    ok.append(check_tag(tag, self.src, str(path), f"{key}[{k}]"))
                except SceneFormatError as exc:
                    errors.append(error_record(str(tag), exc))
            good[key] = ok
        if "test" in good:
            rule = "the file's train / val / test lists"
            split_of = {t: s for s in ("train", "val", "test") for t in good.get(s, [])}
        else:
            rule = (f"no test list in {SPLIT_FILE}: test = the file's val list (the authors' held-out rooms); "
                    f"val = the max(1, round({self.val_fraction:g} · n)) train tags of smallest sha256")
            carved = carve_val(good["train"], self.val_fraction)
            split_of = {t: "val" if t in carved else "train" for t in good["train"]}
            for t in good.get("val", []):
                split_of[t] = "test"
        listed = sum(len(v) for v in good.values())
        rooms = [RoomRef(t, s, str(self.src / t)) for t, s in sorted(split_of.items())]
        splits = {"rule": rule, "file": str(path), "ignored_keys": unknown,
                  "listed_in_two_splits": listed - len(split_of),
                  "counts": {s: sum(1 for r in rooms if r.split == s) for s in ("train", "val", "test")}}
        return RoomList(rooms, errors, splits)

    # ---- per room ------------------------------------------------------------------------------
    def _arrays(self, ref: RoomRef) -> tuple[str, dict]:
        path = Path(ref.folder) / "boxes.npz"
        if not path.is_file():
            raise SceneFormatError(str(path), None, f"tag '{ref.tag}' has no boxes.npz")
        return str(path), load_npz_arrays(within(path, self.src))

    def mesh_path(self, name: str) -> Path | None:
        for candidate in (f"{name}_unpacked.glb", f"{name}.glb"):
            if "/" in candidate or "\\" in candidate or candidate.startswith(".."):
                return None
            p = self.src / "meshes" / candidate
            if p.is_file():
                return within(p, self.src)
        return None

    def _scene(self, ref: RoomRef):
        """(file, the file's arrays, its Scene with repairs and table categories, repair counts)."""
        from spread.importers.release_details import release_category, repair_release_arrays

        file, raw = self._arrays(ref)
        arrays, repairs = repair_release_arrays(raw)
        scene = reference_scene(arrays, file, ref.scene_id)
        named = [release_category(str(a)) for a in scene.asset_id]
        scene.category = np.array([c for c, _ in named])
        scene.extras["category_known"] = np.array([k for _, k in named])
        if "relations" in raw and np.size(raw["relations"]):  # every triple, "Empty" and root ones included
            scene.extras["release_relations"] = np.asarray(raw["relations"]).reshape(-1, 3).astype(np.int64)
        scene.extras["release_regions"] = np.asarray(raw["regions_bbox"]).astype(np.int64)  # as the file has it, root too
        repairs["unknown_categories"] = int(sum(not k for _, k in named))
        return file, arrays, scene, repairs

    def scan(self, ref: RoomRef) -> list[AssetRequest]:
        file, _, scene, _ = self._scene(ref)
        requests = []
        for k, name in enumerate(scene.asset_id.tolist()):
            path = self.mesh_path(name)
            if path is None:
                raise SceneFormatError(file, f"obj_names[{k + 1}]",
                                       f"object '{name}' has no mesh (looked for {self.src / 'meshes' / (name + '_unpacked.glb')})")
            requests.append(AssetRequest(safe_name(name), str(scene.category[k]), "mesh", str(path)))
        return requests

    def scene(self, ref: RoomRef, library, requests: list[AssetRequest]):
        file, arrays, scene, repairs = self._scene(ref)
        scene.asset_id = np.array([r.asset_id for r in requests])
        R = scene.rotation.astype(np.float64)
        offsets = np.array([library[r.asset_id].source.get("canonical_offset", [0.0, 0.0, 0.0]) for r in requests])
        file_centres = np.asarray(arrays["bbox_center"], np.float64)[1:] if "bbox_center" in arrays else offsets
        shift = offsets - file_centres
        scene.translation = (scene.translation.astype(np.float64) + np.einsum("nij,nj->ni", R, shift)).astype(np.float32)
        from spread.importers.mounts import mount_counts, release_mounts
        from spread.relations import scene_aabbs

        lo, _ = scene_aabbs(scene.translation, scene.rotation, [str(a) for a in scene.asset_id], library)
        scene.extras["mount"] = release_mounts(arrays.get("relations", np.zeros((0, 3))), scene.num_objects,
                                               scene.category, lo[:, 1])
        scene.extras["source_tag"] = np.asarray(ref.tag)
        scene.extras["import_source"] = np.asarray(self.name)
        if self.room_type:
            scene.extras["room_type"] = np.asarray(self.room_type)
        return scene, {"bbox_center_differs": int((np.linalg.norm(shift, axis=1) > CENTRE_TOLERANCE).sum()),
                       **mount_counts(scene.extras["mount"]), **repairs}


def read_dataset_stats(path: Path) -> dict | None:
    """The source's ``dataset_stats.txt`` (JSON) or None when absent; errors name the file and, for a value an
    import would use, the key: ``class_labels`` / ``object_types`` lists of names, ``bounds_translations`` six
    finite numbers [min xyz, max xyz] (metres) with min < max (the dataset's stats.json takes them as written)."""
    import math

    if not path.is_file():
        return None
    stats = read_json_object(path)
    for key in ("class_labels", "object_types"):
        names = stats.get(key)
        if names is not None and not (isinstance(names, list) and all(isinstance(n, str) for n in names)):
            raise ValueError(f"{path}: key {key!r}: expected a list of names, got {str(names)[:80]!r}")
    bounds = stats.get("bounds_translations")
    if bounds is not None:
        numbers = isinstance(bounds, list) and len(bounds) == 6 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in bounds)
        if not numbers or any(bounds[i] >= bounds[i + 3] for i in range(3)):
            raise ValueError(f"{path}: key 'bounds_translations': expected six finite numbers [min x, min y, min z, "
                             f"max x, max y, max z] with min < max on each axis, got {str(bounds)[:120]}")
    return stats


register_importer("spread_release", lambda cfg: SpreadRelease(cfg.src, room_type=cfg.room_type,
                                                              val_fraction=cfg.val_fraction))
