"""The Scene record, its ``.npz`` file format, validation, and a reader for the reference release.

Conventions (DESIGN §3): metres, y-up, floor at y = 0. Object ``i`` is placed by
``v_world = rotation[i] @ v_local + translation[i]`` where ``v_local`` is a vertex of the asset's
canonical mesh (centred at its bounding-box centre, y-up), so ``translation[i]`` is the world position
of the canonical bbox centre and ``rotation[i]`` is world-from-local.

Codes: ``spatial[i, j]`` says "i is <code> of j" with
0 right of, 1 left of, 2 in front of, 3 behind, 4 above, 5 below, 6 self (the diagonal);
``physical[i, j]`` is 0 none, 1 "i supports j", 2 contact.

Mounts: ``extras["mount"]`` (N,) int8 says how each object is held (:data:`MOUNT_NAMES`): 0 floor (rests on
the floor), 1 on-object (rests on another object), 2 wall, 3 ceiling (fixed to the building: physics welds
it to the world, gravity and support guidance and ASD leave it alone). A file without the key (older
files, generated rooms) reads as today: every object free, floor or on-object from the support graph
(:func:`scene_mounts`).

Extra arrays (for example ``source`` on generated scenes, or precomputed shape tokens) are kept in
``Scene.extras`` and round-trip through the file unchanged.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Mapping

import numpy as np

from spread.io import atomic_path

if TYPE_CHECKING:  # pragma: no cover
    from spread.assets.library import AssetLibrary

SPATIAL_NAMES = ("right of", "left of", "in front of", "behind", "above", "below", "self")
SPATIAL_RIGHT, SPATIAL_LEFT, SPATIAL_FRONT, SPATIAL_BEHIND, SPATIAL_ABOVE, SPATIAL_BELOW, SPATIAL_SELF = range(7)
NUM_SPATIAL = 7
PHYSICAL_NAMES = ("none", "support", "contact")
PHYSICAL_NONE, PHYSICAL_SUPPORT, PHYSICAL_CONTACT = range(3)
NUM_PHYSICAL = 3

MOUNT_NAMES = ("floor", "on_object", "wall", "ceiling")
MOUNT_FLOOR, MOUNT_ON_OBJECT, MOUNT_WALL, MOUNT_CEILING = range(4)
MOUNT_KEY = "mount"

#: Largest |RᵀR − I| entry accepted for a rotation matrix read from a file.
ROTATION_TOLERANCE = 1e-3

REQUIRED_KEYS = ("scene_id", "asset_id", "category", "translation", "rotation", "spatial", "physical")
OPTIONAL_KEYS = ("room",)


class SceneFormatError(ValueError):
    """A scene file or record breaks the contract; the message names the file, the key and the problem."""

    def __init__(self, source: str, key: str | None, problem: str):
        self.source, self.key, self.problem = source, key, problem
        where = f"{source}: key '{key}'" if key else source
        super().__init__(f"{where}: {problem}")


class ImplausibleSceneError(SceneFormatError):
    """A well-formed scene that is physically absurd (an object kilometres outside its room, a coordinate of
    1e30, a mug a kilometre across): refused by every reader, counted apart by the runs (:class:`Plausibility`)."""


@dataclass(frozen=True)
class Plausibility:
    """Sane bounds every scene read or written is held to (metres). ``max_coordinate``: largest |x|, |y|, |z|
    of a position or room corner; ``room_margin``: how far outside its room's box (``room``) an object's
    centre may be; ``max_extent``: largest size of an asset along any axis (a library record's ``extents``).
    Defaults are generous for rooms (generated and 3D-FRONT objects stay within their room by well under a
    metre); override them with the environment variables of :data:`PLAUSIBILITY_ENV`."""

    max_coordinate: float = 1000.0
    room_margin: float = 10.0
    max_extent: float = 50.0

    @classmethod
    def from_env(cls) -> "Plausibility":
        values = {}
        for name, var in PLAUSIBILITY_ENV.items():
            raw = os.environ.get(var, "").strip()
            if raw:
                try:
                    values[name] = float(raw)
                except ValueError:
                    raise ValueError(f"{var}={raw!r}: not a number of metres") from None
                if not values[name] > 0:
                    raise ValueError(f"{var}={raw!r}: must be > 0 metres")
        return cls(**values)


#: Environment variables that override a :class:`Plausibility` bound (metres).
PLAUSIBILITY_ENV = {"max_coordinate": "SPREAD_MAX_COORDINATE_M", "room_margin": "SPREAD_ROOM_MARGIN_M",
                    "max_extent": "SPREAD_MAX_EXTENT_M"}


def check_asset_extents(asset_id: str, extents, source: str, bounds: Plausibility | None = None) -> None:
    """Raise :class:`ImplausibleSceneError` when an asset's size (metres, per axis) is not finite or over
    ``bounds.max_extent`` (a mesh with a vertex at 1e30, a mug scaled to a kilometre)."""
    b = bounds or Plausibility.from_env()
    extents = np.asarray(extents, np.float64)
    if not np.isfinite(extents).all() or extents.max() > b.max_extent:
        raise ImplausibleSceneError(source, None, f"asset '{asset_id}' is {extents.tolist()} m across, over "
                                                  f"{b.max_extent:g} m: physically implausible, refused (bound set by "
                                                  f"{PLAUSIBILITY_ENV['max_extent']})")


def check_plausible(scene: "Scene", source: str, records=None, bounds: Plausibility | None = None) -> None:
    """Raise :class:`ImplausibleSceneError` (file, key, object, value, the bound and how to change it) when a
    position, the room or an asset's size is outside ``bounds`` (None: :meth:`Plausibility.from_env`)."""
    b = bounds or Plausibility.from_env()

    def fail(key: str, problem: str, var: str) -> None:
        raise ImplausibleSceneError(source, key, f"{problem}: physically implausible, refused "
                                                 f"(bound set by {PLAUSIBILITY_ENV[var]})")

    far = np.abs(scene.translation).max(axis=1)
    if (far > b.max_coordinate).any():
        i = int(np.argmax(far))
        fail("translation", f"object {i} is at {scene.translation[i].tolist()} m, beyond ±{b.max_coordinate:g} m",
             "max_coordinate")
    if scene.room is not None:
        if np.abs(scene.room).max() > b.max_coordinate:
            fail("room", f"room corners {scene.room.tolist()} m reach beyond ±{b.max_coordinate:g} m", "max_coordinate")
        lo, hi = scene.room[0] - b.room_margin, scene.room[1] + b.room_margin
        out = ((scene.translation < lo) | (scene.translation > hi)).any(axis=1)
        if out.any():
            i = int(np.argmax(out))
            fail("translation", f"object {i} at {scene.translation[i].tolist()} m is more than {b.room_margin:g} m "
                                f"outside the room {scene.room.tolist()}", "room_margin")
    if records is not None:
        for i, aid in enumerate(scene.asset_id):
            extents = np.asarray(records[aid].extents, np.float64)
            if not np.isfinite(extents).all() or extents.max() > b.max_extent:
                fail("asset_id", f"object {i}'s asset '{aid}' is {extents.tolist()} m across, over "
                                 f"{b.max_extent:g} m", "max_extent")


@dataclass
class Scene:
    """One scene of N objects (no padding). Shapes and units are those of DESIGN §4."""

    scene_id: str
    asset_id: np.ndarray  # (N,) str
    category: np.ndarray  # (N,) str
    translation: np.ndarray  # (N, 3) float32, metres, world bbox-centre
    rotation: np.ndarray  # (N, 3, 3) float32, world-from-local
    spatial: np.ndarray  # (N, N) int8
    physical: np.ndarray  # (N, N) int8
    room: np.ndarray | None = None  # (2, 3) float32 min, max
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.scene_id = str(self.scene_id)
        self.asset_id = np.asarray(self.asset_id, dtype=str).reshape(-1)
        self.category = np.asarray(self.category, dtype=str).reshape(-1)
        self.translation = np.asarray(self.translation, dtype=np.float32)
        self.rotation = np.asarray(self.rotation, dtype=np.float32)
        self.spatial = np.asarray(self.spatial, dtype=np.int8)
        self.physical = np.asarray(self.physical, dtype=np.int8)
        if self.room is not None:
            self.room = np.asarray(self.room, dtype=np.float32)

    @property
    def num_objects(self) -> int:
        return int(self.asset_id.shape[0])

    def __len__(self) -> int:
        return self.num_objects

    def transforms(self) -> np.ndarray:
        """(N, 4, 4) float64 world-from-local homogeneous transforms."""
        T = np.tile(np.eye(4), (self.num_objects, 1, 1))
        T[:, :3, :3] = self.rotation
        T[:, :3, 3] = self.translation
        return T

    def support_pairs(self) -> np.ndarray:
        """(K, 2) int array of (supporter, supported) index pairs from ``physical``."""
        return np.argwhere(self.physical == PHYSICAL_SUPPORT)

    def with_poses(self, translation: np.ndarray, rotation: np.ndarray, scene_id: str | None = None) -> "Scene":
        """A copy with new poses and the same graph, ids and extras."""
        return Scene(
            scene_id=self.scene_id if scene_id is None else scene_id,
            asset_id=self.asset_id.copy(), category=self.category.copy(),
            translation=np.asarray(translation, np.float32).copy(), rotation=np.asarray(rotation, np.float32).copy(),
            spatial=self.spatial.copy(), physical=self.physical.copy(),
            room=None if self.room is None else self.room.copy(),
            extras={k: np.array(v, copy=True) for k, v in self.extras.items()},
        )

    def validate(self, source: str | None = None, assets: "AssetLibrary | Iterable[str] | None" = None) -> "Scene":
        validate_scene(self, source=source or f"scene '{self.scene_id}'", assets=assets)
        return self

    def to_arrays(self) -> dict[str, np.ndarray]:
        arrays = {
            "scene_id": np.asarray(self.scene_id),
            "asset_id": self.asset_id,
            "category": self.category,
            "translation": self.translation,
            "rotation": self.rotation,
            "spatial": self.spatial,
            "physical": self.physical,
        }
        if self.room is not None:
            arrays["room"] = self.room
        for key, value in self.extras.items():
            if key in arrays:
                raise SceneFormatError(f"scene '{self.scene_id}'", key, "extra key shadows a contract key")
            arrays[key] = np.asarray(value)
        return arrays


def _fail(source: str, key: str | None, problem: str) -> None:
    raise SceneFormatError(source, key, problem)


def support_cycle(supports: np.ndarray) -> list[int]:
    """A cycle of the directed support graph (``supports[i, j]``: i supports j) as [i, j, …, i], or [] when
    there is none (iterative depth-first search)."""
    n = len(supports)
    state = np.zeros(n, np.int8)  # 0 new, 1 on the current path, 2 done
    for root in range(n):
        if state[root]:
            continue
        path, stack = [root], [iter(np.flatnonzero(supports[root]))]
        state[root] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state[nxt] == 1:
                return path[path.index(int(nxt)):] + [int(nxt)]
            elif state[nxt] == 0:
                state[nxt] = 1
                path.append(int(nxt))
                stack.append(iter(np.flatnonzero(supports[nxt])))
    return []


def scene_mounts(scene: Scene) -> np.ndarray:
    """(N,) int8 mount codes of ``scene`` (module docstring): the file's ``mount`` when it has one, else
    on-object for every object something supports and floor for the others."""
    if MOUNT_KEY in scene.extras:
        return np.asarray(scene.extras[MOUNT_KEY], np.int8).reshape(-1)
    supported = (np.asarray(scene.physical) == PHYSICAL_SUPPORT).any(axis=0)
    return np.where(supported, MOUNT_ON_OBJECT, MOUNT_FLOOR).astype(np.int8)


def welded_objects(scene: Scene) -> np.ndarray:
    """(N,) bool: the objects fixed to the building (wall or ceiling mounts), which physics welds to the world."""
    return np.isin(scene_mounts(scene), (MOUNT_WALL, MOUNT_CEILING))


def validate_scene(scene: Scene, source: str, assets: "AssetLibrary | Iterable[str] | None" = None) -> None:
    """Check every contract of DESIGN §4; raise :class:`SceneFormatError` naming source, key, problem."""
    n = scene.num_objects
    if not scene.scene_id:
        _fail(source, "scene_id", "empty scene id")
    if n == 0:
        _fail(source, "asset_id", "scene has no objects (N = 0)")
    shapes = {
        "asset_id": (scene.asset_id, (n,)),
        "category": (scene.category, (n,)),
        "translation": (scene.translation, (n, 3)),
        "rotation": (scene.rotation, (n, 3, 3)),
        "spatial": (scene.spatial, (n, n)),
        "physical": (scene.physical, (n, n)),
    }
    if scene.room is not None:
        shapes["room"] = (scene.room, (2, 3))
    for key, (arr, shape) in shapes.items():
        if arr.shape != shape:
            _fail(source, key, f"shape {tuple(arr.shape)} does not match N = {n} (expected {shape})")
    for key in ("translation", "rotation") + (("room",) if scene.room is not None else ()):
        arr = getattr(scene, key)
        bad = ~np.isfinite(arr)
        if bad.any():
            idx = np.argwhere(bad)[0].tolist()
            _fail(source, key, f"non-finite value {arr[tuple(idx)]} at index {idx}")
    R = scene.rotation.astype(np.float64)
    ortho_err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    det = np.linalg.det(R)
    worst = int(np.argmax(ortho_err))
    if ortho_err[worst] > ROTATION_TOLERANCE:
        _fail(source, "rotation", f"object {worst} is not orthonormal (max |RᵀR − I| = {ortho_err[worst]:.2e})")
    if (det <= 0).any():
        i = int(np.argmax(det <= 0))
        _fail(source, "rotation", f"object {i} has determinant {det[i]:.3f} (a reflection, not a rotation)")
    if scene.room is not None and (scene.room[1] < scene.room[0]).any():
        _fail(source, "room", f"max {scene.room[1].tolist()} is below min {scene.room[0].tolist()}")
    diag = np.eye(n, dtype=bool)
    sp = scene.spatial
    if (sp[diag] != SPATIAL_SELF).any():
        i = int(np.argmax(sp[diag] != SPATIAL_SELF))
        _fail(source, "spatial", f"diagonal entry ({i},{i}) is {sp[i, i]}, expected {SPATIAL_SELF} (self)")
    off = sp[~diag]
    if ((off < 0) | (off >= SPATIAL_SELF)).any():
        bad = np.argwhere(((sp < 0) | (sp >= SPATIAL_SELF)) & ~diag)[0].tolist()
        _fail(source, "spatial", f"code {sp[tuple(bad)]} at {bad} out of range 0..5 off the diagonal")
    ph = scene.physical
    if ((ph < 0) | (ph >= NUM_PHYSICAL)).any():
        bad = np.argwhere((ph < 0) | (ph >= NUM_PHYSICAL))[0].tolist()
        _fail(source, "physical", f"code {ph[tuple(bad)]} at {bad} out of range 0..{NUM_PHYSICAL - 1}")
    if (ph[diag] != PHYSICAL_NONE).any():
        i = int(np.argmax(ph[diag] != PHYSICAL_NONE))
        _fail(source, "physical", f"object {i} has a physical relation with itself")
    if MOUNT_KEY in scene.extras:
        mount = np.asarray(scene.extras[MOUNT_KEY])
        if mount.shape != (n,) or mount.dtype.kind not in "iu":
            _fail(source, MOUNT_KEY, f"expected (N,) = ({n},) integer codes, got shape {mount.shape} dtype {mount.dtype}")
        if ((mount < 0) | (mount >= len(MOUNT_NAMES))).any():
            i = int(np.argmax((mount < 0) | (mount >= len(MOUNT_NAMES))))
            _fail(source, MOUNT_KEY, f"object {i} has mount code {mount[i]}, expected 0..{len(MOUNT_NAMES) - 1} "
                                     f"({', '.join(MOUNT_NAMES)})")
    cycle = support_cycle(ph == PHYSICAL_SUPPORT)
    if cycle:
        _fail(source, "physical", "support cycle " + " → ".join(str(i) for i in cycle)
              + " (i supports j supports … i): support must be a forest rooted at the floor")
    if assets is not None:
        known = assets if hasattr(assets, "__contains__") else set(assets)
        for i, aid in enumerate(scene.asset_id):
            if aid not in known:
                _fail(source, "asset_id", f"object {i} references unknown asset '{aid}'")
        records = getattr(assets, "records", None)
        if records is not None:
            for i, (aid, cat) in enumerate(zip(scene.asset_id, scene.category)):
                if records[aid].category != cat:
                    _fail(source, "category", f"object {i} says '{cat}' but asset '{aid}' is '{records[aid].category}'")
    check_plausible(scene, source, getattr(assets, "records", None) if assets is not None else None)


def write_scene(scene: Scene, path: str | os.PathLike, validate: bool = True) -> Path:
    """Write ``scene`` to ``path`` (``.npz``, uncompressed) atomically; returns the path."""
    path = Path(path)
    if path.suffix != ".npz":
        raise SceneFormatError(str(path), None, "scene files must end in .npz")
    if validate:
        validate_scene(scene, source=str(path))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **scene.to_arrays())
    return path


def read_scene(path: str | os.PathLike, assets: "AssetLibrary | Iterable[str] | None" = None,
               validate: bool = True) -> Scene:
    """Read and validate one scene file; errors name the file and key."""
    path = Path(path)
    src = str(path)
    if not path.exists() and not path.is_symlink():
        _fail(src, None, "file does not exist")
    from spread.io import InputFileError, check_input_file
    from spread.safe_load import UnsafeFileError, load_npz

    try:  # a regular file of plausible size (a link to /dev/zero or a FIFO is refused, not read)
        check_input_file(path, root=path.parent)
    except InputFileError as exc:
        raise SceneFormatError(src, None, str(exc).removeprefix(f"{path}: ")) from None

    try:
        with load_npz(path) as data:
            arrays = {k: data[k] for k in data.files}
    except UnsafeFileError as exc:  # an object array: it would need unpickling
        raise SceneFormatError(src, None, str(exc).removeprefix(f"{path}: ")) from None
    except Exception as exc:  # zip errors, truncated file
        raise SceneFormatError(src, None, f"not a readable .npz file ({type(exc).__name__}: {exc})") from exc
    return scene_from_arrays(arrays, source=src, assets=assets, validate=validate)


def scene_from_arrays(arrays: Mapping[str, np.ndarray], source: str = "<arrays>",
                      assets: "AssetLibrary | Iterable[str] | None" = None, validate: bool = True) -> Scene:
    for key, value in arrays.items():  # a zip whose members are not .npy files gives raw bytes
        if not isinstance(value, np.ndarray):
            _fail(source, key, f"not a numpy array (a {type(value).__name__}): the file is a zip archive but not "
                               f"an .npz of arrays")
    for key in REQUIRED_KEYS:
        if key not in arrays:
            _fail(source, key, "missing required key")
    for key in ("asset_id", "category", "scene_id"):
        if arrays[key].dtype.kind not in "US":
            _fail(source, key, f"expected strings, got dtype {arrays[key].dtype}")
        if arrays[key].dtype.kind == "U":
            try:  # a lone surrogate ('chair\udcff') is no text: every writer of JSON, HTML or a picture fails on it
                "".join(arrays[key].reshape(-1).tolist()).encode("utf-8")
            except UnicodeEncodeError as exc:
                _fail(source, key, f"holds a string that is not valid text ({exc.reason} at {exc.start})")
    for key in ("translation", "rotation") + (("room",) if "room" in arrays else ()):
        if arrays[key].dtype.kind not in "fiu":
            _fail(source, key, f"expected numbers, got dtype {arrays[key].dtype}")
    for key in ("spatial", "physical"):
        arr = arrays[key]
        if arr.dtype.kind == "f":
            if not np.all(np.isfinite(arr)) or not np.all(arr == np.round(arr)):
                _fail(source, key, "codes must be integers")
        elif arr.dtype.kind not in "iu":
            _fail(source, key, f"expected integer codes, got dtype {arr.dtype}")
        if arr.size and (arr.min() < -128 or arr.max() > 127):
            _fail(source, key, f"code {arr.max() if arr.max() > 127 else arr.min()} out of range")
    if arrays["scene_id"].shape != ():
        _fail(source, "scene_id", f"expected a scalar string, got shape {arrays['scene_id'].shape}")
    scene = Scene(
        scene_id=str(arrays["scene_id"]),
        asset_id=arrays["asset_id"], category=arrays["category"],
        translation=arrays["translation"], rotation=arrays["rotation"],
        spatial=arrays["spatial"], physical=arrays["physical"],
        room=arrays.get("room"),
        extras={k: np.asarray(v) for k, v in arrays.items() if k not in REQUIRED_KEYS + OPTIONAL_KEYS},
    )
    if validate:
        validate_scene(scene, source=source, assets=assets)
    return scene


def list_scene_files(folder: str | os.PathLike) -> list[Path]:
    """Sorted scene files (``*.npz``) of a folder; raises if the folder does not exist."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: not a folder of scene files")
    return sorted(p for p in folder.glob("*.npz") if not p.name.startswith("."))


def load_npz_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` file, read with ``allow_pickle=False``.

    Raises :class:`SceneFormatError` naming the file for an unreadable file, and naming the key for an
    object array (pickled Python objects are never unpickled: save strings as unicode arrays instead,
    ``np.asarray(names, dtype=str)``).
    """
    from spread.safe_load import UnsafeFileError, load_npz

    src = str(path)
    try:
        data = load_npz(path)
    except Exception as exc:
        raise SceneFormatError(src, None, f"not a readable .npz file ({type(exc).__name__}: {exc})") from exc
    arrays = {}
    with data:
        for key in data.files:
            try:
                arrays[key] = data[key]
            except UnsafeFileError as exc:
                raise SceneFormatError(src, key, "stored as an object array (pickled Python objects); refused "
                                       "without unpickling — store strings as a unicode array "
                                       "(np.asarray(values, dtype=str))") from exc
            except Exception as exc:
                raise SceneFormatError(src, key, f"unreadable array ({type(exc).__name__}: {exc})") from exc
    return arrays
