"""``source=threed_front``: InstructScene's (and ATISS', DiffuScene's) preprocessed 3D-FRONT rooms.

Layout of ``src`` (one room type per folder, as those projects preprocess it)::

    <houseUUID>_<RoomId>/boxes.npz   one room
    dataset_stats.txt                JSON: ``class_labels`` (the one-hot columns), ``object_types``, bounds

and ``splits=CSV``: lines ``RoomId,train|val|test`` (the projects' ``*_threed_front_splits.csv``; a line
may also name the whole folder). Rooms whose RoomId the CSV does not list are skipped and counted. When
it has no val rows, val is carved from train as for the release (``val_fraction``, by tag hash).

``boxes.npz`` keys used: ``class_labels`` (N, C) one-hot, ``translations`` (N, 3) bbox centres relative
to the floor plan's bbox centre (metres, y-up, floor y = 0), ``sizes`` (N, 3) **half** extents, ``angles``
(N, 1) rotation about +y in radians, ``jids`` (N,) 3D-FUTURE model ids, ``floor_plan_vertices`` /
``floor_plan_faces`` / ``floor_plan_centroid`` (kept, centred, as extras and the ``room`` bounds),
``scene_type`` (kept). Read with ``allow_pickle=False``.

Frames: the projects place a model by ``v_world = R_y(θ) · (s ⊙ v_model − c) + t`` with ``R_y(θ)`` the
right-handed rotation about +y ([[cos θ, 0, sin θ], [0, 1, 0], [−sin θ, 0, cos θ]]; their row-vector code
writes its transpose), so ``rotation = R_y(angle)`` and ``translation = translations``.

Mounts: lamp classes hang from the ceiling, wall-hung classes are on the wall, the rest rest on the floor or
on another object (:func:`spread.importers.mounts.front_mounts`; counts ``mount_*`` in the manifest).

Meshes: with ``future_models=DIR`` each object is ``DIR/<jid>/raw_model.obj`` scaled per axis to
``2 · sizes`` (rounded to 1 mm: asset id ``<jid>-<x>x<y>x<z>`` in mm); one decomposition per model is
reused for every scale. Without it an oriented box of ``2 · sizes`` stands in (asset ``box-<class>-…``)
and the manifest says so.

Graph: one rule for every pair. 3D-FRONT has no physical relations, and InstructScene's cached
``relations.npy`` uses its own spatial rule (oriented footprints, lamps always above, nothing beyond 3 m)
for some pairs only; mixing it with the platform's rule in one graph would make GRecall of the ground
truth fall below 1 by definition. So every spatial and physical code is the platform's, from the posed
meshes (:func:`spread.relations.scene_spatial_codes`, :func:`spread.relations.physical_codes`; the
manifest's ``relations_rule``), and a room's ``relations.npy``, when present, is only compared with them
(counts ``file_pairs`` / ``file_pairs_equal`` in the manifest's ``room_counts``).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from spread.importers.base import (SPLITS, AssetRequest, RoomList, RoomRef, Source, carve_val, error_record,
                                   within)
from spread.io import check_input_file, read_json_object, read_text_checked, safe_name
from spread.safe_load import load_npz
from spread.scene import (
    SPATIAL_ABOVE, SPATIAL_BEHIND, SPATIAL_BELOW, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT, SPATIAL_SELF, Scene,
    SceneFormatError, load_npz_arrays,
)
from spread.importers.registry import register_importer

ROOM_TYPES = ("bedroom", "livingroom", "diningroom", "library")  # ATISS ships a split file for each
#: InstructScene's predicate vocabulary (index order) → our spatial codes (DESIGN §3).
INSTRUCTSCENE_PREDICATES = {
    0: SPATIAL_ABOVE, 1: SPATIAL_LEFT, 2: SPATIAL_FRONT, 3: SPATIAL_LEFT, 4: SPATIAL_FRONT,
    5: SPATIAL_BELOW, 6: SPATIAL_RIGHT, 7: SPATIAL_BEHIND, 8: SPATIAL_RIGHT, 9: SPATIAL_BEHIND,
}
REVERSE = {SPATIAL_ABOVE: SPATIAL_BELOW, SPATIAL_BELOW: SPATIAL_ABOVE, SPATIAL_LEFT: SPATIAL_RIGHT,
           SPATIAL_RIGHT: SPATIAL_LEFT, SPATIAL_FRONT: SPATIAL_BEHIND, SPATIAL_BEHIND: SPATIAL_FRONT}


def rotation_y(angles: np.ndarray) -> np.ndarray:
    """(N, 3, 3) right-handed rotations about +y by ``angles`` (N,) radians."""
    c, s = np.cos(angles), np.sin(angles)
    R = np.zeros((len(angles), 3, 3))
    R[:, 0, 0], R[:, 0, 2], R[:, 1, 1], R[:, 2, 0], R[:, 2, 2] = c, s, 1.0, -s, c
    return R


def read_splits(path: Path) -> dict[str, str]:
    """``{id: split}`` of a splits CSV; errors name the file and line."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: splits file missing (lines 'RoomId,train|val|test')")
    out: dict[str, str] = {}
    import io

    with io.StringIO(read_text_checked(path), newline="") as fh:
        for line_no, row in enumerate(csv.reader(fh), start=1):
            row = [c.strip() for c in row]
            if not row or not any(row):
                continue
            if len(row) < 2 or row[1] not in SPLITS:
                if line_no == 1:
                    continue  # a header line
                raise ValueError(f"{path}: line {line_no}: expected 'RoomId,train|val|test', got {','.join(row)!r}")
            if row[0] in out and out[row[0]] != row[1]:  # a room in two splits: the import would leak it between them
                raise ValueError(f"{path}: line {line_no}: room {row[0]!r} is listed in {out[row[0]]!r} and "
                                 f"{row[1]!r}; give each room one split")
            out[row[0]] = row[1]
    return out


def room_id_of(tag: str) -> str:
    """The RoomId of a ``<houseUUID>_<RoomId>`` folder name (the part after the first ``_``)."""
    return tag.split("_", 1)[1] if "_" in tag else tag


def size_mm(extents: np.ndarray) -> str:
    return "x".join(f"{int(round(1000 * v)):04d}" for v in extents)


class ThreedFront(Source):
    """InstructScene's 3D-FRONT layout (module docstring)."""

    name = "threed_front"
    spatial_from_file = False
    relations_rule = ("the platform's (spread.relations): spatial from posed-mesh AABBs, physical from posed "
                      "meshes, every pair; InstructScene's relations.npy is compared, not used")

    def __init__(self, src: str | Path, splits: str | Path, room_type: str, future_models: str | Path | None = None,
                 val_fraction: float = 0.05):
        self.src = Path(src)
        self.val_fraction = float(val_fraction)
        if not self.src.is_dir():
            raise FileNotFoundError(f"src={self.src}: not a folder")
        if not splits:
            raise ValueError("source=threed_front needs splits=CSV (lines 'RoomId,train|val|test')")
        self.splits_path = Path(splits)
        if room_type not in ROOM_TYPES:
            raise ValueError(f"source=threed_front: room_type={room_type!r}, expected one of {', '.join(ROOM_TYPES)}")
        self.room_type = room_type
        self.future_models = Path(future_models) if future_models else None
        if self.future_models is not None and not self.future_models.is_dir():
            raise FileNotFoundError(f"future_models={self.future_models}: not a folder")
        stats_path = self.src / "dataset_stats.txt"
        if not stats_path.is_file():
            raise FileNotFoundError(f"{stats_path}: missing (it names the one-hot class_labels columns)")
        from spread.importers.spread_release import read_dataset_stats

        self.stats = read_dataset_stats(stats_path)
        self.class_labels = [str(c) for c in self.stats.get("class_labels") or []]
        self.object_types = [str(c) for c in self.stats.get("object_types") or []]
        if not self.class_labels and not self.object_types:
            raise ValueError(f"{stats_path}: key 'class_labels' missing or empty")
        self._columns: dict | None = None  # class_columns(), memoised

    def info(self) -> dict:
        return {"source": self.name, "src": str(self.src), "splits": str(self.splits_path),
                "room_type": self.room_type,
                "future_models": str(self.future_models) if self.future_models else None,
                "meshes": "3D-FUTURE raw_model.obj scaled to the file's sizes" if self.future_models
                else "oriented boxes of the file's sizes (no future_models given)",
                "graph": self.relations_rule, "class_columns": self.class_columns()}

    def rooms(self) -> RoomList:
        split_of = read_splits(self.splits_path)
        rooms, errors, skipped = [], [], 0
        for folder in sorted(p for p in self.src.iterdir() if p.is_dir()):
            tag = folder.name
            split = split_of.get(tag, split_of.get(room_id_of(tag)))
            if split is None:
                skipped += 1
                continue
            rooms.append(RoomRef(tag, split, str(folder)))
        rule = f"the splits file's RoomId → split ({self.splits_path})"
        if not any(r.split == "val" for r in rooms):  # training needs a val split
            carved = carve_val([r.tag for r in rooms if r.split == "train"], self.val_fraction)
            rooms = [RoomRef(r.tag, "val", r.folder) if r.tag in carved else r for r in rooms]
            rule += (f"; no val rows: val = the max(1, round({self.val_fraction:g} · n)) train rooms of "
                     f"smallest sha256")
        splits = {"rule": rule, "file": str(self.splits_path),
                  "not_in_splits": skipped,
                  "counts": {s: sum(1 for r in rooms if r.split == s) for s in SPLITS}}
        return RoomList(rooms, errors, splits)

    def _arrays(self, ref: RoomRef) -> tuple[str, dict]:
        path = Path(ref.folder) / "boxes.npz"
        if not path.is_file():
            raise SceneFormatError(str(path), None, f"room '{ref.tag}' has no boxes.npz")
        file = str(path)
        arrays = load_npz_arrays(within(path, self.src))
        for key in ("class_labels", "translations", "sizes", "angles"):
            if key not in arrays:
                raise SceneFormatError(file, key, "missing required key of the 3D-FRONT boxes.npz layout")
        labels = arrays["class_labels"]
        if labels.ndim != 2 or labels.dtype.kind not in "fiub":
            raise SceneFormatError(file, "class_labels", f"expected a one-hot (N, C) array, got shape {labels.shape}")
        n = labels.shape[0]
        if n == 0:
            raise SceneFormatError(file, "class_labels", "room has no objects")
        for key, shape in (("translations", (n, 3)), ("sizes", (n, 3))):
            if arrays[key].shape != shape:
                raise SceneFormatError(file, key, f"shape {arrays[key].shape}, expected {shape} (N = {n} from class_labels)")
        if arrays["angles"].reshape(-1).shape != (n,):
            raise SceneFormatError(file, "angles", f"shape {arrays['angles'].shape}, expected ({n}, 1)")
        for key in ("translations", "sizes", "angles"):
            if arrays[key].dtype.kind not in "fiu":
                raise SceneFormatError(file, key, f"expected numbers, got dtype {arrays[key].dtype}")
            bad = ~np.isfinite(arrays[key].astype(np.float64))
            if bad.any():
                idx = np.argwhere(bad)[0].tolist()
                raise SceneFormatError(file, key, f"non-finite value at index {idx}")
        if (arrays["sizes"] <= 0).any():
            idx = np.argwhere(arrays["sizes"] <= 0)[0].tolist()
            raise SceneFormatError(file, "sizes", f"half extent {arrays['sizes'][tuple(idx)]} ≤ 0 at index {idx}")
        if "jids" in arrays and (arrays["jids"].shape != (n,) or arrays["jids"].dtype.kind not in "US"):
            raise SceneFormatError(file, "jids", f"expected (N,) = ({n},) strings, got shape {arrays['jids'].shape} "
                                                 f"dtype {arrays['jids'].dtype}")
        return file, arrays

    def class_columns(self) -> dict:
        """The names of the files' one-hot columns (memoised; in the manifest's ``source``).

        Upstream writes ``dataset_stats.txt`` from train + val but one-hot encodes with train + val + test
        classes, so a class seen only in test widens every file beyond ``class_labels``. The width is taken
        from the files (the most common one); when it exceeds the stats' list, the stats' classes are mapped
        by name onto the columns that train and val rooms use (every stats class occurs there, by how upstream
        made the list; both lists in the same sorted order), trailing ``start`` / ``end`` onto the last
        columns, and each remaining column is named ``unknown_<column>`` and listed under ``extra``."""
        if self._columns is None:
            self._columns = self._resolve_columns()
        return self._columns

    def _resolve_columns(self) -> dict:
        from collections import Counter

        widths: Counter = Counter()
        used: set[int] = set()
        for ref in self.rooms().rooms:
            try:
                with load_npz(within(Path(ref.folder) / "boxes.npz", self.src)) as f:
                    labels = np.asarray(f["class_labels"])
            except Exception:  # noqa: BLE001  (the room fails on its own, naming its file, when imported)
                continue
            if labels.ndim != 2 or not labels.shape[0] or labels.dtype.kind not in "fiub":
                continue
            widths[labels.shape[1]] += 1
            if ref.split in ("train", "val"):
                used.update(int(i) for i, m in zip(labels.argmax(1), labels.max(1)) if m > 0)
        stats = self.class_labels or self.object_types
        width = widths.most_common(1)[0][0] if widths else len(stats)
        out = {"width": width, "stats_classes": len(stats), "names": None, "extra": [], "error": None}
        if width in (len(self.class_labels), len(self.object_types)):
            out["names"] = self.class_labels if len(self.class_labels) == width else self.object_types
            return out
        tail = []
        for token in reversed(stats):
            if token in ("start", "end") and len(tail) < 2:
                tail.insert(0, token)
            else:
                break
        real = stats[:len(stats) - len(tail)]
        n_real = width - len(tail)
        known = sorted(c for c in used if c < n_real)
        if width < len(stats) or len(known) != len(real):
            out["error"] = (f"the files have {width} one-hot columns, dataset_stats.txt {len(self.class_labels)} "
                            f"class_labels and {len(self.object_types)} object_types; train and val rooms use "
                            f"{len(known)} of the columns, so the stats' {len(real)} classes cannot be placed by name")
            return out
        names = [f"unknown_{c}" for c in range(n_real)] + tail
        for column, name in zip(known, real):
            names[column] = name
        out["names"] = names
        out["extra"] = [n for c, n in enumerate(names[:n_real]) if c not in set(known)]
        return out

    def categories(self, file: str, labels: np.ndarray) -> list[str]:
        width = labels.shape[1]
        names = self.class_labels if len(self.class_labels) == width else (
            self.object_types if len(self.object_types) == width else None)
        columns = self.class_columns() if names is None else {"error": None}
        if names is None and width == columns["width"]:
            names = columns["names"]
        if names is None:
            raise SceneFormatError(file, "class_labels", f"{width} columns, but dataset_stats.txt has "
                                                         f"{len(self.class_labels)} class_labels and "
                                                         f"{len(self.object_types)} object_types"
                                                         + (f" ({columns['error']})" if columns["error"] else ""))
        finite = np.isfinite(labels).all(1) if labels.dtype.kind in "fc" else np.ones(len(labels), bool)
        if not finite.all():  # NaN is not > 0 and argmax picks it: the row was read as another class
            k = int(np.argwhere(~finite)[0][0])
            raise SceneFormatError(file, "class_labels", f"object {k} has a non-finite value "
                                                         f"({labels[k][~np.isfinite(labels[k])][0]}); expected one-hot "
                                                         f"rows")
        hot = (labels > 0).sum(1)
        if (hot > 1).any():  # a multi-hot row would be read as its first class, and its assets as another room's
            k = int(np.argwhere(hot > 1)[0][0])
            raise SceneFormatError(file, "class_labels", f"object {k} has {int(hot[k])} classes set; expected one-hot "
                                                         f"rows")
        index = labels.argmax(1)
        out = []
        for k, i in enumerate(index):
            name = names[int(i)]
            if name in ("start", "end") or labels[k].max() <= 0:
                raise SceneFormatError(file, "class_labels", f"object {k} has class '{name}' (not an object)")
            out.append(name)
        return out

    def scan(self, ref: RoomRef) -> list[AssetRequest]:
        file, arrays = self._arrays(ref)
        cats = self.categories(file, arrays["class_labels"])
        extents = np.round(2.0 * arrays["sizes"].astype(np.float64), 3)
        extents = np.maximum(extents, 0.001)
        requests = []
        for k, (cat, ext) in enumerate(zip(cats, extents)):
            size = tuple(float(v) for v in ext)
            if self.future_models is None:
                requests.append(AssetRequest(safe_name(f"box-{cat}-{size_mm(ext)}"), cat, "box", size=size))
                continue
            if "jids" not in arrays:
                raise SceneFormatError(file, "jids", "missing: future_models was given, so every object needs its jid")
            jid = str(arrays["jids"][k])
            path = self.future_models / jid / "raw_model.obj"
            if not jid or "/" in jid or "\\" in jid or jid in (".", "..") or not path.is_file():
                raise SceneFormatError(file, f"jids[{k}]", f"object '{jid}' has no mesh (looked for {path})")
            within(path, self.future_models, file, f"jids[{k}]")
            requests.append(AssetRequest(safe_name(f"{jid}-{size_mm(ext)}"), cat, "mesh", str(path), size))
        return requests

    def file_spatial(self, ref: RoomRef, n: int) -> tuple[np.ndarray, int] | None:
        """(spatial codes with -1 where the file says nothing, pairs filled) from ``relations.npy``, or None."""
        path = Path(ref.folder) / "relations.npy"
        if not path.is_file():
            return None
        try:
            rel = np.load(check_input_file(within(path, self.src)), allow_pickle=False)
        except ValueError as exc:
            raise SceneFormatError(str(path), None, f"unreadable or an object array (refused): {exc}") from exc
        codes = np.full((n, n), -1, np.int64)
        if rel.size:
            if rel.dtype.kind not in "iu" or rel.ndim != 2 or rel.shape[1] != 3:
                raise SceneFormatError(str(path), None, f"expected (K, 3) integer triples, got {rel.shape} {rel.dtype}")
            for s, p, o in rel.tolist():
                if not (0 <= s < n and 0 <= o < n) or p not in INSTRUCTSCENE_PREDICATES:
                    continue  # virtual root relations and out-of-vocabulary predicates
                codes[s, o] = INSTRUCTSCENE_PREDICATES[p]
                codes[o, s] = REVERSE[INSTRUCTSCENE_PREDICATES[p]]
        np.fill_diagonal(codes, SPATIAL_SELF)
        return codes, int((codes < 0).sum())

    def scene(self, ref: RoomRef, library, requests: list[AssetRequest]):
        from spread.relations import physical_codes, scene_aabbs, scene_spatial_codes

        file, arrays = self._arrays(ref)
        n = len(requests)
        T = arrays["translations"].astype(np.float64)
        R = rotation_y(arrays["angles"].astype(np.float64).reshape(-1))
        ids = [r.asset_id for r in requests]
        spatial = scene_spatial_codes(T, R, ids, library)
        given = self.file_spatial(ref, n)
        compared = {}
        if given is not None:
            known = (given[0] >= 0) & ~np.eye(n, dtype=bool)
            compared = {"file_pairs": int(known.sum()), "file_pairs_equal": int((known & (given[0] == spatial)).sum())}
        physical = physical_codes(T, R, ids, library).codes
        lo, hi = scene_aabbs(T, R, ids, library)
        extras = {"source_tag": np.asarray(ref.tag), "import_source": np.asarray(self.name),
                  "room_type": np.asarray(self.room_type)}
        room_lo, room_hi = lo.min(0), hi.max(0)
        if "floor_plan_vertices" in arrays and "floor_plan_centroid" in arrays:
            fv = arrays["floor_plan_vertices"].astype(np.float64)
            fc = arrays["floor_plan_centroid"].astype(np.float64).reshape(-1)
            if fv.ndim == 2 and fv.shape[1] == 3 and fc.shape == (3,) and np.isfinite(fv).all() and np.isfinite(fc).all():
                centred = fv - fc
                extras["floor_plan_vertices"] = centred.astype(np.float32)
                if "floor_plan_faces" in arrays and arrays["floor_plan_faces"].dtype.kind in "iu":
                    extras["floor_plan_faces"] = arrays["floor_plan_faces"].astype(np.int32)
                room_lo = np.minimum(room_lo, centred.min(0))
                room_hi = np.maximum(room_hi, centred.max(0))
        room_lo[1] = min(0.0, room_lo[1])
        for key in ("scene_type", "scene_id", "scene_uid"):
            if key in arrays and arrays[key].dtype.kind in "US" and arrays[key].shape == ():
                extras[f"source_{key}"] = np.asarray(str(arrays[key]))
        if "jids" in arrays:
            extras["jids"] = arrays["jids"].astype(str)
        from spread.importers.mounts import front_mounts, mount_counts

        extras["mount"] = front_mounts([r.category for r in requests], physical, lo[:, 1])
        scene = Scene(ref.scene_id, np.array(ids), np.array([r.category for r in requests]), T.astype(np.float32),
                      R.astype(np.float32), spatial.astype(np.int8), physical, room=np.stack([room_lo, room_hi]),
                      extras=extras)
        return scene, {"file_spatial": given is not None, **compared, **mount_counts(extras["mount"])}


__all__ = ["ThreedFront", "read_splits", "rotation_y", "error_record"]


register_importer("threed_front", lambda cfg: ThreedFront(cfg.src, cfg.splits, cfg.room_type, cfg.future_models,
                                                          cfg.val_fraction))
