"""Objects as the baselines see them: class, box size, heading about y, plus the rest of the rotation held fixed.

ATISS, DiffuScene and InstructScene describe an object by its class, its bounding-box size, the box centre
and one angle θ about the vertical axis (3D-FRONT furniture stands upright). Our scenes pose objects with a
full rotation R (world-from-local, y-up; DESIGN §3), which this module splits as

    R = R_y(θ) · T,    θ = argmax_φ tr(R_y(φ)ᵀ R) = atan2(R[0,2] − R[2,0], R[0,0] + R[2,2]),

where R_y(θ) = [[cos θ, 0, sin θ], [0, 1, 0], [−sin θ, 0, cos θ]] (x → −z for θ = π/2) and T = R_y(−θ)·R is
the object's *rest orientation* (the identity for an upright object; a lying bottle's tilt otherwise). θ is
the y-rotation nearest to R, so for an upright object T = I exactly.

What a baseline predicts is θ (and the box centre); the class, the box size and T are part of the given
object set and are held fixed at sampling, so every method places the same objects (the comparison is
about placement; a baseline's own paper would also generate classes and sizes). The box size is the
axis-aligned extent of the asset's canonical box after T: ``size = |T| · extents`` (metres).

Normalisation: box centres use the dataset's translation bounds (``x[..., :3]`` of the batch is already in
[−1, 1]); sizes map ``[size_min, size_max]`` (metres, over every asset of the library and every axis) to
[−1, 1]; angles are (cos θ, sin θ) or θ/π.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import torch

from spread.box_geometry import box_size, rot_y, split_rotation, yaw_of  # noqa: F401 (the baselines' names)
from spread.data.rotation import rot6d_to_matrix
from spread.model.poses import denormalize


class Objects(NamedTuple):
    """The baselines' view of a batch (B scenes, N objects padded; values at padding are meaningless)."""

    mask: torch.Tensor  # (B, N) bool, real objects
    category: torch.Tensor  # (B, N) long, class index (0 at padding)
    translation: torch.Tensor  # (B, N, 3) box centre, normalised to [−1, 1] by the dataset bounds
    yaw: torch.Tensor  # (B, N) θ in (−π, π]
    tilt: torch.Tensor  # (B, N, 3, 3) rest orientation T (R = R_y(θ)·T)
    size: torch.Tensor  # (B, N, 3) box size, metres (full extents, not half)


def objects_of(batch: dict) -> Objects:
    """Class, normalised centre, heading, rest orientation and size of every object of a collated batch
    (keys ``x``, ``mask``, ``category_index``, ``extents``; :mod:`spread.data`)."""
    if "extents" not in batch:
        raise KeyError("baselines need the batch key 'extents' (asset box sizes; spread.data.SceneDataset "
                       "provides it)")
    x = batch["x"].float()
    mask = batch["mask"].bool()
    rotation = rot6d_to_matrix(x[..., 3:9])
    yaw, tilt = split_rotation(rotation)
    eye = torch.eye(3, dtype=x.dtype, device=x.device)
    tilt = torch.where(mask[..., None, None], tilt, eye)
    size = box_size(batch["extents"].to(x), tilt) * mask[..., None]
    category = torch.where(mask, batch["category_index"].long(), torch.zeros_like(batch["category_index"].long()))
    return Objects(mask, category, x[..., :3], torch.where(mask, yaw, torch.zeros_like(yaw)), tilt, size)


def poses(translation_norm: torch.Tensor, yaw: torch.Tensor, tilt: torch.Tensor, mask: torch.Tensor,
          bounds: torch.Tensor):
    """Predicted box centres (normalised) and headings → :class:`spread.model.module.Poses` (metres,
    world-from-local ``R_y(θ)·T``; 0 and the identity at padding)."""
    from spread.model.module import Poses

    mask = mask.bool()
    translation = denormalize(translation_norm.float(), bounds.float())
    rotation = rot_y(yaw.float()) @ tilt.float()
    eye = torch.eye(3, dtype=rotation.dtype, device=rotation.device).expand_as(rotation)
    return Poses(torch.where(mask[..., None], translation, 0.0), torch.where(mask[..., None, None], rotation, eye))


def normalize_size(size: torch.Tensor, size_bounds: Sequence[float]) -> torch.Tensor:
    """Metres → [−1, 1] over ``size_bounds`` = (min, max) metres (clipped)."""
    lo, hi = float(size_bounds[0]), float(size_bounds[1])
    return (2 * (size.clamp(lo, hi) - lo) / (hi - lo) - 1).to(size.dtype)


def denormalize_size(size: torch.Tensor, size_bounds: Sequence[float]) -> torch.Tensor:
    lo, hi = float(size_bounds[0]), float(size_bounds[1])
    return (size + 1) / 2 * (hi - lo) + lo


def world_boxes(objects_translation: torch.Tensor, size: torch.Tensor, yaw: torch.Tensor,
                bounds: torch.Tensor) -> torch.Tensor:
    """(B, N, 7) boxes [centre x, y, z (metres), size x, y, z (metres), θ] from normalised centres."""
    centre = denormalize(objects_translation, bounds.to(objects_translation))
    return torch.cat([centre, size.to(centre), yaw.to(centre)[..., None]], dim=-1)
