"""The release's ``boxes.npz`` as upstream reads it: categories from a table, and repairs instead of refusals.

**Categories** (:func:`release_category`): an asset name such as ``RoboTHOR_dining_table_mella`` or
``TV_Stand_201_1`` is lower-cased, its ``RoboTHOR_`` prefix and ``_unpacked`` suffix dropped, and the
longest run of leading words found in :data:`CATEGORY_TABLE` (ProcTHOR / AI2-THOR object types) names its
category (``dining_table``, ``tv_stand``). A name the table does not know keeps the old rule (its words
without trailing numbers) and is listed as unknown (the manifest's ``room_counts`` count them; the scene
keeps ``category_known`` per object), never guessed silently.

**Repairs** (:func:`repair_release_arrays`, each counted; upstream reads such files as they are):

* a rotation that is not orthonormal within the scene contract's 1e-3 but within :data:`NEAR_ROTATION`
  is replaced by its nearest rotation (SVD, determinant +1);
* an off-diagonal "self" code in ``regions_bbox`` becomes the reverse of its transposed entry when that is a
  direction, else the horizontal sector of the two bbox centres (the platform's rule without boxes);
* a support cycle among the ``relations`` triples is broken at its weakest support: the one whose supported
  object's centre is lowest relative to its supporter's (a supporter above what it supports is the least
  plausible); repeated until no cycle is left.

The file's ``relations`` triples themselves — "Empty" ones and those of the root entry 0 included — are
kept in the scene as ``extras["release_relations"]`` (the model and an export back to the release layout can
use them).
"""

from __future__ import annotations

import numpy as np

from spread.scene import (
    PHYSICAL_SUPPORT, SPATIAL_ABOVE, SPATIAL_BEHIND, SPATIAL_BELOW, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT,
    SPATIAL_SELF,
)

#: Largest |RᵀR − I| entry repaired (larger: refused by the scene contract as before).
NEAR_ROTATION = 0.05
REVERSE = {SPATIAL_RIGHT: SPATIAL_LEFT, SPATIAL_LEFT: SPATIAL_RIGHT, SPATIAL_FRONT: SPATIAL_BEHIND,
           SPATIAL_BEHIND: SPATIAL_FRONT, SPATIAL_ABOVE: SPATIAL_BELOW, SPATIAL_BELOW: SPATIAL_ABOVE}

#: ProcTHOR / AI2-THOR object types as the release's asset names spell them (lower case, words joined by _)
#: → the platform's category name.
CATEGORY_TABLE = {
    "alarm_clock": "alarm_clock", "apple": "apple", "armchair": "armchair", "arm_chair": "armchair",
    "baseball_bat": "baseball_bat", "basket_ball": "basketball", "bathtub": "bathtub", "bed": "bed",
    "book": "book", "bottle": "bottle", "bowl": "bowl", "box": "box", "bread": "bread", "candle": "candle",
    "cart": "cart", "cd": "cd", "cell_phone": "cell_phone", "chair": "chair", "cloth": "cloth",
    "coffee_machine": "coffee_machine", "coffee_table": "coffee_table", "counter_top": "counter_top",
    "countertop": "counter_top", "credit_card": "credit_card", "cup": "cup", "desk": "desk",
    "desk_lamp": "desk_lamp", "dining_table": "dining_table", "dish_sponge": "dish_sponge", "dog_bed": "dog_bed",
    "dresser": "dresser", "egg": "egg", "floor_lamp": "floor_lamp", "fork": "fork", "fridge": "fridge",
    "garbage_can": "garbage_can", "house_plant": "house_plant", "kettle": "kettle", "key_chain": "key_chain",
    "knife": "knife", "ladle": "ladle", "laptop": "laptop", "laundry_hamper": "laundry_hamper", "lettuce": "lettuce",
    "microwave": "microwave", "mirror": "mirror", "mug": "mug", "newspaper": "newspaper", "ottoman": "ottoman",
    "painting": "painting", "pan": "pan", "pen": "pen", "pencil": "pencil", "pepper_shaker": "pepper_shaker",
    "pillow": "pillow", "plate": "plate", "plunger": "plunger", "pot": "pot", "potato": "potato",
    "remote": "remote_control", "remote_control": "remote_control", "safe": "safe", "salt_shaker": "salt_shaker",
    "shelf": "shelf", "shelving_unit": "shelving_unit", "side_table": "side_table", "sink": "sink",
    "soap_bottle": "soap_bottle", "sofa": "sofa", "spatula": "spatula", "spoon": "spoon", "spray_bottle": "spray_bottle",
    "statue": "statue", "stool": "stool", "table": "table", "table_top_decor": "table_top_decor",
    "teddy_bear": "teddy_bear", "television": "television", "tennis_racket": "tennis_racket", "tissue_box": "tissue_box",
    "toilet": "toilet", "toilet_paper": "toilet_paper", "tomato": "tomato", "towel": "towel",
    "towel_statue": "statue", "tv_stand": "tv_stand", "vacuum_cleaner": "vacuum_cleaner", "vase": "vase",
    "watch": "watch", "watering_can": "watering_can", "wine_bottle": "wine_bottle",
}


def _words(asset_name: str) -> list[str]:
    name = asset_name.lower().replace("_unpacked", "")
    if name.startswith("robothor_"):
        name = name[len("robothor_"):]
    return [w for w in name.split("_") if w]


def release_category(asset_name: str) -> tuple[str, bool]:
    """(category, known) of a release asset name (module docstring)."""
    words = _words(asset_name)
    for k in range(len(words), 0, -1):
        key = "_".join(words[:k])
        if key in CATEGORY_TABLE:
            return CATEGORY_TABLE[key], True
    while len(words) > 1 and words[-1].isdigit():
        words.pop()
    return ("_".join(words) or asset_name.lower()), False


def nearest_rotation(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _sector(d: np.ndarray) -> int:
    theta = np.arctan2(d[2], d[0])
    if -np.pi / 4 <= theta < np.pi / 4:
        return SPATIAL_RIGHT
    if np.pi / 4 <= theta < 3 * np.pi / 4:
        return SPATIAL_FRONT
    if -3 * np.pi / 4 <= theta < -np.pi / 4:
        return SPATIAL_BEHIND
    return SPATIAL_LEFT


def acyclic_supports(rel: np.ndarray, heights: np.ndarray) -> tuple[np.ndarray, int]:
    """(which rows of the (M, 3) triples ``rel`` [supporter, predicate, supported] to keep, how many distinct support
    pairs were dropped) so that the support pairs form no cycle; ``heights``: the objects' y (index 0 the root).

    A pair whose supported object stands higher than its supporter (dy > 0) never closes a cycle with others like
    it (heights rise along each), so all of those stay; the others are added from the most plausible (largest dy)
    down, each unless its supported object already reaches its supporter — the pair of a cycle whose supporter
    stands highest is the one dropped, as breaking one found cycle at a time did, but in one pass: the pairs that
    reach each other are a boolean matrix updated per pair (O(N²) numpy work a pair), where finding and breaking
    cycles one at a time rebuilt the support matrix and searched it again per dropped pair (a 300-object room whose
    objects all support each other ran for hours). Rows that are not support pairs of two objects are kept as they
    are."""
    n1 = len(heights)
    keep = np.ones(len(rel), bool)
    pair = (rel[:, 1] == PHYSICAL_SUPPORT) & (rel[:, 0] >= 1) & (rel[:, 2] >= 1) & (rel[:, 0] < n1) \
        & (rel[:, 2] < n1) & (rel[:, 0] != rel[:, 2])
    rows = np.flatnonzero(pair)
    if not len(rows):
        return keep, 0
    s, o = rel[rows, 0], rel[rows, 2]
    dy = heights[o] - heights[s]
    rising = dy > 0
    reach = np.zeros((n1, n1), bool)  # reach[a, b]: b is reachable from a through kept pairs
    reach[s[rising], o[rising]] = True
    while True:  # the rising pairs' closure: log2(N) boolean products
        wider = reach | ((reach.astype(np.float32) @ reach.astype(np.float32)) > 0)
        if (wider == reach).all():
            break
        reach = wider
    dropped: set[tuple[int, int]] = set()
    for k in np.flatnonzero(~rising)[np.argsort(-dy[~rising], kind="stable")]:
        a, b = int(s[k]), int(o[k])
        if reach[b, a]:  # b already reaches a: a → b would close a cycle
            keep[rows[k]] = False
            dropped.add((a, b))
            continue
        sources, targets = reach[:, a].copy(), reach[b].copy()
        sources[a] = targets[b] = True
        reach |= np.outer(sources, targets)
    return keep, len(dropped)


def repair_release_arrays(arrays: dict) -> tuple[dict, dict]:
    """(repaired copy of the arrays, counts ``rotations_orthonormalised``, ``self_codes_replaced``,
    ``support_cycles_broken``); arrays it cannot read are returned as they are (the reader names the problem)."""
    out = dict(arrays)
    counts = {"rotations_orthonormalised": 0, "self_codes_replaced": 0, "support_cycles_broken": 0}
    R = np.asarray(arrays.get("R_bbox", np.zeros((0, 3, 3))))
    if R.ndim == 3 and len(R) and R.shape[1:] == (3, 3) and R.dtype.kind in "fiu" and np.isfinite(R).all():
        R = R.astype(np.float64).copy()
        err = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
        fix = (err > 1e-6) & (err <= NEAR_ROTATION)
        fix[0] = False  # the placeholder
        for i in np.flatnonzero(fix):
            R[i] = nearest_rotation(R[i])
        counts["rotations_orthonormalised"] = int(fix.sum())
        out["R_bbox"] = R
    T = np.asarray(arrays.get("T_bbox", np.zeros((0, 3))), np.float64)
    regions = np.asarray(arrays.get("regions_bbox", np.zeros((0, 0))))
    if regions.ndim == 2 and regions.shape[0] == regions.shape[1] == len(T) and regions.dtype.kind in "iu":
        regions = regions.copy()
        for i, j in np.argwhere(regions == SPATIAL_SELF):
            if i == j or i == 0 or j == 0:
                continue
            back = int(regions[j, i])
            regions[i, j] = REVERSE[back] if back in REVERSE else _sector(T[i] - T[j])
            counts["self_codes_replaced"] += 1
        out["regions_bbox"] = regions
    rel = np.asarray(arrays.get("relations", np.zeros((0, 3))))
    if rel.size and rel.dtype.kind in "iu" and rel.size % 3 == 0 and len(T):
        rel = rel.reshape(-1, 3).astype(np.int64)
        keep, broken = acyclic_supports(rel, T[:, 1] if T.ndim == 2 and T.shape[1] > 1 else np.zeros(len(T)))
        rel = rel[keep]
        counts["support_cycles_broken"] = broken
        out["relations"] = rel
    return out, counts
