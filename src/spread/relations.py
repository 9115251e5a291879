"""Spatial relation codes (DESIGN §3) — the one implementation used by data, GRecall and Stability.

``spatial_codes(aabb_min, aabb_max)[i, j]`` says "i is <code> of j", from each object's world
axis-aligned bounding box (AABB) of its posed mesh:

* horizontal sector from θ = atan2(dz, dx) of the AABB centres' difference c_i − c_j:
  right of −π/4 ≤ θ < π/4; in front of π/4 ≤ θ < 3π/4; behind −3π/4 ≤ θ < −π/4; left of otherwise;
* vertical override when the xz-centre of either lies inside the other's xz footprint (the AABB's xz
  rectangle, boundary included) and they do not overlap vertically beyond
  :data:`VERTICAL_TOLERANCE` (i's bottom ≥ j's top − 5 mm: above; i's top ≤ j's bottom + 5 mm: below).

Everything is vectorised over all ordered pairs (numpy, or torch when given tensors).
Physical (support/contact) detection from posed meshes lives in :mod:`spread.relations_physical`
once implemented there; this module holds the spatial part.
"""

from __future__ import annotations

import math

import numpy as np

from spread.scene import (
    SPATIAL_ABOVE, SPATIAL_BEHIND, SPATIAL_BELOW, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT, SPATIAL_SELF,
)

#: Vertical overlap (metres) still counted as "above"/"below" (an object resting on another touches it).
VERTICAL_TOLERANCE = 0.005


def spatial_codes(aabb_min, aabb_max):
    """(N, N) int8 spatial codes from world AABBs (N, 3) min and max, metres, y-up.

    Accepts numpy arrays (returns numpy) or torch tensors of shape (..., N, 3) (returns a torch
    int8 tensor of shape (..., N, N)); torch is used by the model side for batched scenes.
    """
    if not isinstance(aabb_min, np.ndarray):
        return _spatial_codes_torch(aabb_min, aabb_max)
    lo = np.asarray(aabb_min, np.float64)
    hi = np.asarray(aabb_max, np.float64)
    if lo.shape != hi.shape or lo.shape[-1] != 3:
        raise ValueError(f"spatial_codes: aabb_min {lo.shape} and aabb_max {hi.shape} must both be (..., N, 3)")
    c = 0.5 * (lo + hi)
    d = c[..., :, None, :] - c[..., None, :, :]  # c_i − c_j
    theta = np.arctan2(d[..., 2], d[..., 0])
    codes = np.full(theta.shape, SPATIAL_LEFT, dtype=np.int8)
    q = math.pi / 4
    codes[(theta >= -q) & (theta < q)] = SPATIAL_RIGHT
    codes[(theta >= q) & (theta < 3 * q)] = SPATIAL_FRONT
    codes[(theta >= -3 * q) & (theta < -q)] = SPATIAL_BEHIND

    cx, cz = c[..., 0], c[..., 2]
    # centre of i inside footprint of j
    i_in_j = ((cx[..., :, None] >= lo[..., None, :, 0]) & (cx[..., :, None] <= hi[..., None, :, 0])
              & (cz[..., :, None] >= lo[..., None, :, 2]) & (cz[..., :, None] <= hi[..., None, :, 2]))
    stacked = i_in_j | np.swapaxes(i_in_j, -1, -2)
    above = lo[..., :, None, 1] >= hi[..., None, :, 1] - VERTICAL_TOLERANCE
    below = hi[..., :, None, 1] <= lo[..., None, :, 1] + VERTICAL_TOLERANCE
    codes[stacked & above] = SPATIAL_ABOVE
    codes[stacked & below & ~above] = SPATIAL_BELOW
    n = codes.shape[-1]
    idx = np.arange(n)
    codes[..., idx, idx] = SPATIAL_SELF
    return codes


def _spatial_codes_torch(aabb_min, aabb_max):
    import torch

    lo, hi = aabb_min.double(), aabb_max.double()
    c = 0.5 * (lo + hi)
    d = c[..., :, None, :] - c[..., None, :, :]
    theta = torch.atan2(d[..., 2], d[..., 0])
    q = math.pi / 4
    codes = torch.full(theta.shape, SPATIAL_LEFT, dtype=torch.int8, device=theta.device)
    codes[(theta >= -q) & (theta < q)] = SPATIAL_RIGHT
    codes[(theta >= q) & (theta < 3 * q)] = SPATIAL_FRONT
    codes[(theta >= -3 * q) & (theta < -q)] = SPATIAL_BEHIND
    cx, cz = c[..., 0], c[..., 2]
    i_in_j = ((cx[..., :, None] >= lo[..., None, :, 0]) & (cx[..., :, None] <= hi[..., None, :, 0])
              & (cz[..., :, None] >= lo[..., None, :, 2]) & (cz[..., :, None] <= hi[..., None, :, 2]))
    stacked = i_in_j | i_in_j.transpose(-1, -2)
    above = lo[..., :, None, 1] >= hi[..., None, :, 1] - VERTICAL_TOLERANCE
    below = hi[..., :, None, 1] <= lo[..., None, :, 1] + VERTICAL_TOLERANCE
    codes[stacked & above] = SPATIAL_ABOVE
    codes[stacked & below & ~above] = SPATIAL_BELOW
    n = codes.shape[-1]
    idx = torch.arange(n, device=codes.device)
    codes[..., idx, idx] = SPATIAL_SELF
    return codes


def posed_aabbs(translation: np.ndarray, rotation: np.ndarray, local_vertices: list[np.ndarray]):
    """World AABBs (N, 3) min and max of posed point sets.

    ``local_vertices[i]`` are canonical-frame points of object i (pass the convex-hull vertices: a
    mesh's AABB equals its hull's, and hulls are much smaller).
    """
    n = len(local_vertices)
    lo = np.empty((n, 3))
    hi = np.empty((n, 3))
    for i, v in enumerate(local_vertices):
        w = np.asarray(v, np.float64) @ np.asarray(rotation[i], np.float64).T + np.asarray(translation[i], np.float64)
        lo[i], hi[i] = w.min(0), w.max(0)
    return lo, hi
