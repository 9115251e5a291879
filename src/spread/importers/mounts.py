"""How each imported object is held (``Scene.extras["mount"]``, :data:`spread.scene.MOUNT_NAMES`).

* **3D-FRONT** (:func:`front_mounts`): the lamp classes InstructScene / ATISS keep (``ceiling_lamp``,
  ``pendant_lamp``; :data:`CEILING_CLASSES`) hang from the ceiling, wall-hung classes (:data:`WALL_CLASSES`)
  are on the wall; every other object rests on what the platform's support graph says (on-object when
  something supports it, else floor). A ceiling or wall class whose bottom is on the floor (within
  :data:`FLOOR_TOLERANCE`) stands on the floor.
* **SPREAD release** (:func:`release_mounts`): from the file's support triples over its N+1 entries: an
  object supported by another object rests on it; one supported by the root entry (index 0), or unsupported
  with its bottom on the floor, stands on the floor; an unsupported object above the floor is held by the
  building: ceiling when its category names a lamp or light hanging from above (:data:`CEILING_WORDS`), wall
  otherwise.
"""

from __future__ import annotations

import numpy as np

from spread.scene import MOUNT_CEILING, MOUNT_FLOOR, MOUNT_NAMES, MOUNT_ON_OBJECT, MOUNT_WALL, PHYSICAL_SUPPORT

#: 3D-FRONT classes hung from the ceiling (ATISS / InstructScene keep them unless run with --without_lamps).
CEILING_CLASSES = frozenset({"ceiling_lamp", "pendant_lamp", "chandelier", "ceiling_fan"})
#: Classes hung on a wall (not in the standard 3D-FRONT vocabularies; other preprocessings and ProcTHOR have them).
WALL_CLASSES = frozenset({"wall_lamp", "wall_shelf", "wall_cabinet", "wall_clock", "mirror", "painting",
                          "picture", "picture_frame", "poster", "wall_tv", "television_wall"})
#: Category words of a release object, unsupported and above the floor, that hangs from the ceiling.
CEILING_WORDS = ("ceiling", "pendant", "chandelier", "hanging")
#: An object whose lowest point is at most this high (metres) stands on the floor.
FLOOR_TOLERANCE = 0.02


def _from_support(physical: np.ndarray) -> np.ndarray:
    supported = (np.asarray(physical) == PHYSICAL_SUPPORT).any(axis=0)
    return np.where(supported, MOUNT_ON_OBJECT, MOUNT_FLOOR).astype(np.int8)


def front_mounts(categories, physical: np.ndarray, bottoms: np.ndarray) -> np.ndarray:
    """(N,) mount codes of a 3D-FRONT room (module docstring); ``bottoms``: each object's lowest y, metres."""
    mount = _from_support(physical)
    lifted = np.asarray(bottoms, np.float64) > FLOOR_TOLERANCE
    for k, cat in enumerate(categories):
        name = str(cat).lower()
        if name in CEILING_CLASSES and lifted[k]:
            mount[k] = MOUNT_CEILING
        elif name in WALL_CLASSES and lifted[k]:
            mount[k] = MOUNT_WALL
    return mount


def release_mounts(relations: np.ndarray, n: int, categories, bottoms: np.ndarray) -> np.ndarray:
    """(N,) mount codes of a release room (module docstring) from its ``relations`` triples over N+1 entries."""
    rel = np.asarray(relations).reshape(-1, 3).astype(np.int64) if np.size(relations) else np.zeros((0, 3), np.int64)
    sup = rel[(rel[:, 1] == PHYSICAL_SUPPORT) & (rel[:, 0] != rel[:, 2])]
    on_object = np.zeros(n, bool)
    on_root = np.zeros(n, bool)
    for s, _, o in sup.tolist():
        if 1 <= o <= n:
            (on_root if s == 0 else on_object)[o - 1] = True
    lifted = np.asarray(bottoms, np.float64) > FLOOR_TOLERANCE
    mount = np.full(n, MOUNT_FLOOR, np.int8)
    for k in range(n):
        if on_object[k]:
            mount[k] = MOUNT_ON_OBJECT
        elif not on_root[k] and lifted[k]:
            name = str(categories[k]).lower()
            mount[k] = MOUNT_CEILING if any(w in name for w in CEILING_WORDS) else MOUNT_WALL
    return mount


def mount_counts(mount: np.ndarray) -> dict:
    """``{"mount_<name>": count}`` for the manifest's room counts."""
    return {f"mount_{name}": int((np.asarray(mount) == code).sum()) for code, name in enumerate(MOUNT_NAMES)}
