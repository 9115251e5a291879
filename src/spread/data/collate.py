"""Batching scenes of different sizes: pad to the batch's largest N and return a mask.

Padding values (the reference's codes, §1.3 of the reference notes):

=============== ============================ ==================================================
key             padded shape                 value at padding
=============== ============================ ==================================================
mask            (B, N) bool                  False (True on real objects)
x               (B, N, 9)                    0
spatial         (B, N, N) int64              7 = :data:`SPATIAL_PAD` (vocabulary 0..6 + pad, size 8)
physical        (B, N, N) int64              3 = :data:`PHYSICAL_PAD` (vocabulary 0..2 + pad, size 4)
asset_index     (B, N) int64                 −1 = :data:`INDEX_PAD` (never a valid index: use the
category_index  (B, N) int64                 mask, or map −1 to a pad embedding, before looking up)
shape_index     (B, N) int64                 −1
points, normals (B, N, M, 3)                 0
extents         (B, N, 3)                    0
room            (B, 2, 3)                    (per scene, stacked: no padding)
scene_id        list of B str
num_objects     (B,) int64                   N of each scene
=============== ============================ ==================================================

Pairs between a real and a padded object, in both directions, get the pad codes. Keys of
:data:`SCENE_KEYS` are per-scene tensors of one shape, stacked. Other tensors whose first dimension is
the scene's N are zero-padded along it; anything else is collected into a list.
:func:`pad_objects` pads a collated batch further, to a larger N, with the same values (a compiled training step
pads each batch to a bucket of object counts, so that it compiles once per bucket, not once per N).
"""

from __future__ import annotations

from typing import Sequence

import torch

from spread.scene import NUM_PHYSICAL, NUM_SPATIAL

SPATIAL_PAD = NUM_SPATIAL  # 7
PHYSICAL_PAD = NUM_PHYSICAL  # 3
INDEX_PAD = -1

#: key → (pad value, number of leading object dimensions)
PAD_SPEC: dict[str, tuple[float, int]] = {
    "x": (0.0, 1),
    "spatial": (SPATIAL_PAD, 2),
    "physical": (PHYSICAL_PAD, 2),
    "asset_index": (INDEX_PAD, 1),
    "category_index": (INDEX_PAD, 1),
    "shape_index": (INDEX_PAD, 1),
    "points": (0.0, 1),
    "normals": (0.0, 1),
    "extents": (0.0, 1),
}
#: Per-scene tensors (not per object): stacked along a new batch dimension.
SCENE_KEYS = ("room",)


def _pad(tensors: Sequence[torch.Tensor], sizes: Sequence[int], n_max: int, value, object_dims: int) -> torch.Tensor:
    first = tensors[0]
    tail = tuple(first.shape[object_dims:])
    out = torch.full((len(tensors),) + (n_max,) * object_dims + tail, value, dtype=first.dtype)
    for b, (t, n) in enumerate(zip(tensors, sizes)):
        if tuple(t.shape[object_dims:]) != tail:
            raise ValueError(f"collate: item {b} has trailing shape {tuple(t.shape[object_dims:])}, item 0 {tail}")
        out[(b,) + (slice(0, n),) * object_dims] = t
    return out


def collate_scenes(items: Sequence[dict]) -> dict:
    """Batch :class:`~spread.data.dataset.SceneDataset` items (padding as in the module docstring)."""
    if not items:
        raise ValueError("collate_scenes: empty batch")
    sizes = [int(it["x"].shape[0]) for it in items]
    n_max = max(sizes)
    batch: dict = {
        "mask": torch.arange(n_max)[None, :] < torch.tensor(sizes)[:, None],
        "num_objects": torch.tensor(sizes, dtype=torch.long),
    }
    for key in items[0]:
        values = [it[key] for it in items]
        if key in PAD_SPEC:
            value, dims = PAD_SPEC[key]
            batch[key] = _pad(values, sizes, n_max, value, dims)
        elif key in SCENE_KEYS:
            batch[key] = torch.stack([torch.as_tensor(v) for v in values])
        elif all(isinstance(v, torch.Tensor) and v.dim() > 0 and v.shape[0] == n for v, n in zip(values, sizes)):
            batch[key] = _pad(values, sizes, n_max, 0, 1)
        else:
            batch[key] = list(values)
    return batch


def pad_objects(batch: dict, n: int) -> dict:
    """A collated batch (:func:`collate_scenes`) padded to ``n`` ≥ its N objects, with the values and the mask
    :func:`collate_scenes` would have given a batch whose largest scene had ``n`` objects; the same device and
    dtypes. Per-scene keys (:data:`SCENE_KEYS`, ``num_objects``), lists and other values are left as they are."""
    if "mask" not in batch or "x" not in batch:
        raise ValueError(f"pad_objects: not a collated batch (keys {sorted(batch)}): 'mask' and 'x' are needed")
    size = int(batch["x"].shape[1])
    if n < size:
        raise ValueError(f"pad_objects: cannot pad a batch of {size} objects to {n}")
    if n == size:
        return batch
    out = dict(batch)
    for key, value in batch.items():
        if not isinstance(value, torch.Tensor) or key in SCENE_KEYS or key == "num_objects" or value.dim() < 2:
            continue
        fill, dims = (False, 1) if key == "mask" else PAD_SPEC.get(key, (0, 1))
        if any(value.shape[d] != size for d in range(1, dims + 1)):
            continue  # not per object
        shape = (value.shape[0],) + (n,) * dims + tuple(value.shape[dims + 1:])
        padded = value.new_full(shape, fill)
        padded[(slice(None),) + (slice(0, size),) * dims] = value
        out[key] = padded
    return out
