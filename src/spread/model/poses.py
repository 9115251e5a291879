"""Normalised node states ↔ poses, and posed point clouds (DESIGN §3 frames).

A node state ``x`` (..., 9) is ``[normalised translation (3) in [−1, 1], rot6d (6)]`` (see
:mod:`spread.data.stats` and :mod:`spread.data.rotation`). ``bounds`` is the (6,) tensor
``[min xyz, max xyz]`` of ``stats.json`` in metres. Noisy states are fine: translations are mapped
back linearly without clipping, rotations through Gram–Schmidt (always a proper rotation).
"""

from __future__ import annotations

import torch

from spread.data.rotation import rot6d_to_matrix


def denormalize(x_translation: torch.Tensor, bounds: torch.Tensor) -> torch.Tensor:
    """(..., 3) normalised → metres, ``(x + 1)/2·(max − min) + min`` (no clipping)."""
    lo, hi = bounds[:3].to(x_translation), bounds[3:].to(x_translation)
    return (x_translation + 1) / 2 * (hi - lo) + lo


def denormalize_affine(bounds: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(offset, scale), each (3,) metres, with ``denormalize(x, bounds) = offset + scale·x``: the bounds' centre
    and half-range (what the pose kernels take as one multiply-add)."""
    lo, hi = bounds[:3], bounds[3:]
    return (hi + lo) / 2, (hi - lo) / 2


def poses_from_state(x: torch.Tensor, bounds: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 9) node states → translation (..., 3) metres, rotation (..., 3, 3) world-from-local."""
    return denormalize(x[..., :3], bounds), rot6d_to_matrix(x[..., 3:9])


def pose_points(points: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """Canonical points (B, N, M, 3) → world ``R·p + t`` (B, N, M, 3); also for normals with t = 0."""
    return torch.einsum("bnij,bnmj->bnmi", rotation, points) + translation[..., None, :]


def points_aabb(world_points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """World AABB (min, max), each (B, N, 3), of posed point clouds (B, N, M, 3)."""
    return world_points.amin(dim=-2), world_points.amax(dim=-2)
