"""Augmentation that keeps the graphs true: the 8 symmetries of a square floor (quarter turns about the
vertical axis, and a mirror), applied to a whole room with its spatial codes remapped.

Transform ``k`` ∈ 0..7 (:data:`NUM_TRANSFORMS`): first a mirror x → 2c_x − x when ``k ≥ 4``, then ``k % 4``
quarter turns about the vertical line through the centre c (metres, y-up, DESIGN §3). One quarter turn is
the rotation by +90° about y, Q = R_y(90°): (x, z) ↦ (z, −x) about c, exactly (a permutation with a sign, no
rounding). Poses follow the room: t ↦ Q (t − c) + c, R ↦ Q R (world-from-local), and the mirror
S = diag(−1, 1, 1) maps R ↦ S R S, a proper rotation of the *mirrored* asset (local x → −x), so a mirrored
room's items also mirror each object's canonical points and normals (:func:`mirror_local`): every mirrored
room is a room of mirrored assets whose poses, points and graphs agree exactly.

Spatial codes (``spatial[i, j]``: "i is … of j", from θ = atan2(dz, dx) of the world AABB centres; DESIGN §3):
a quarter turn maps θ ↦ θ − π/2, so right → behind → left → front → right; the mirror maps θ ↦ π − θ, so right
↔ left; above, below and self are unchanged (heights and footprint containment are kept: a world AABB of a
posed mesh turns and mirrors with it under these maps). Physical codes (support, contact) are unchanged.
The only pairs a remap can miss are exact ties of the sector rule (|dx| = |dz|, or equal centres), which the
recomputation puts on the other side of a boundary; the test on generated rooms finds none.

The translation bounds must contain every transformed room: :func:`square_bounds` widens x and z to one
square around the xz centre of the dataset's bounds (rooms rotate about that centre).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from spread.scene import (
    SPATIAL_ABOVE, SPATIAL_BEHIND, SPATIAL_BELOW, SPATIAL_FRONT, SPATIAL_LEFT, SPATIAL_RIGHT, SPATIAL_SELF, Scene,
)

NUM_TRANSFORMS = 8

#: code ↦ code under one quarter turn Q = R_y(+90°) (index = old code).
QUARTER_TURN_CODES = np.empty(SPATIAL_SELF + 1, np.int8)
QUARTER_TURN_CODES[[SPATIAL_RIGHT, SPATIAL_BEHIND, SPATIAL_LEFT, SPATIAL_FRONT]] = [
    SPATIAL_BEHIND, SPATIAL_LEFT, SPATIAL_FRONT, SPATIAL_RIGHT]
QUARTER_TURN_CODES[[SPATIAL_ABOVE, SPATIAL_BELOW, SPATIAL_SELF]] = [SPATIAL_ABOVE, SPATIAL_BELOW, SPATIAL_SELF]

#: code ↦ code under the mirror x → −x.
MIRROR_CODES = np.arange(SPATIAL_SELF + 1, dtype=np.int8)
MIRROR_CODES[[SPATIAL_RIGHT, SPATIAL_LEFT]] = [SPATIAL_LEFT, SPATIAL_RIGHT]

#: The mirror in the world and in each object's frame.
MIRROR = np.diag([-1.0, 1.0, 1.0])
#: One quarter turn about y, R_y(+90°): (x, y, z) ↦ (z, y, −x).
QUARTER_TURN = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


def check_transform(k: int) -> tuple[bool, int]:
    """(mirrored, quarter turns) of transform ``k``; a clear error outside 0..7."""
    if not 0 <= int(k) < NUM_TRANSFORMS:
        raise ValueError(f"augmentation transform must be in 0..{NUM_TRANSFORMS - 1}, got {k}")
    return int(k) >= 4, int(k) % 4


def transform_matrix(k: int) -> np.ndarray:
    """(3, 3) world map of transform ``k`` (about the origin): Q^turns · S^mirrored."""
    mirrored, turns = check_transform(k)
    A = MIRROR.copy() if mirrored else np.eye(3)
    for _ in range(turns):
        A = QUARTER_TURN @ A
    return A


def code_table(k: int) -> np.ndarray:
    """(7,) code ↦ code of transform ``k``: the mirror's table, then the quarter turn's, ``k % 4`` times."""
    mirrored, turns = check_transform(k)
    table = MIRROR_CODES.copy() if mirrored else np.arange(SPATIAL_SELF + 1, dtype=np.int8)
    for _ in range(turns):
        table = QUARTER_TURN_CODES[table]
    return table


def remap_spatial(spatial: np.ndarray, k: int) -> np.ndarray:
    """Spatial codes (..., N, N), values 0..6, of a room after transform ``k`` (same dtype)."""
    codes = np.asarray(spatial)
    if codes.size and (codes.min() < 0 or codes.max() > SPATIAL_SELF):
        raise ValueError(f"remap_spatial: codes must be in 0..{SPATIAL_SELF}, got {codes.min()}..{codes.max()}")
    return code_table(k)[codes.astype(np.int64)].astype(codes.dtype)


def _apply_xz(points: np.ndarray, k: int, centre: Sequence[float]) -> np.ndarray:
    """World points (..., 3) under transform ``k`` about the vertical line through ``centre`` (cx, cz):
    exact sign flips and swaps of the offsets from the centre."""
    mirrored, turns = check_transform(k)
    cx, cz = float(centre[0]), float(centre[1])
    out = np.array(points, dtype=np.float64, copy=True)
    dx, dz = out[..., 0] - cx, out[..., 2] - cz
    if mirrored:
        dx = -dx
    for _ in range(turns):
        dx, dz = dz, -dx
    out[..., 0], out[..., 2] = dx + cx, dz + cz
    return out


def transform_poses(translation: np.ndarray, rotation: np.ndarray, k: int,
                    centre: Sequence[float] = (0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Translations (N, 3) and world-from-local rotations (N, 3, 3) after transform ``k`` about ``centre``
    (cx, cz), float64: t ↦ A (t − c) + c, R ↦ A R (S if mirrored), A = :func:`transform_matrix`."""
    mirrored, _ = check_transform(k)
    A = transform_matrix(k)
    R = A @ np.asarray(rotation, np.float64)
    if mirrored:
        R = R @ MIRROR
    return _apply_xz(translation, k, centre), R


def mirror_local(points: np.ndarray, k: int) -> np.ndarray:
    """Canonical points or normals (..., 3) of the assets as transform ``k`` sees them: x → −x when mirrored."""
    mirrored, _ = check_transform(k)
    if not mirrored:
        return points
    out = np.array(points, copy=True)
    out[..., 0] = -out[..., 0]
    return out


def transform_scene(scene: Scene, k: int, centre: Sequence[float] = (0.0, 0.0)) -> Scene:
    """The room after transform ``k`` about ``centre`` (cx, cz): poses, room box and spatial codes; the
    physical codes, ids and extras as they are. A mirrored room's objects are the mirrored assets
    (:func:`mirror_local` gives their points)."""
    if k == 0:
        return scene
    T, R = transform_poses(scene.translation, scene.rotation, k, centre)
    out = scene.with_poses(T, R)
    out.spatial = remap_spatial(scene.spatial, k)
    if scene.room is not None:
        corners = _apply_xz(np.asarray(scene.room, np.float64), k, centre)
        out.room = np.stack([corners.min(0), corners.max(0)]).astype(np.float32)
    return out


def square_bounds(bounds: Sequence[float]) -> list[float]:
    """Translation bounds [min xyz, max xyz] widened in x and z to one square around their xz centre, so
    that every transform about that centre keeps translations inside; y unchanged."""
    b = np.asarray(bounds, np.float64).reshape(6)
    cx, cz = (b[0] + b[3]) / 2, (b[2] + b[5]) / 2
    r = max(b[3] - b[0], b[5] - b[2]) / 2
    return [cx - r, b[1], cz - r, cx + r, b[4], cz + r]


def bounds_centre(bounds: Sequence[float]) -> tuple[float, float]:
    """(cx, cz) of translation bounds."""
    b = np.asarray(bounds, np.float64).reshape(6)
    return float((b[0] + b[3]) / 2), float((b[2] + b[5]) / 2)
