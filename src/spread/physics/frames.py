"""Scene poses (bbox-centre ``t``, world-from-local ``R``) ↔ pybullet body poses (centre of mass).

A body's frame is its asset's principal inertial frame (see :mod:`spread.physics.shapes`):
``v_canonical = com + A · v_body`` with ``com`` (3,) and ``A`` (3, 3) per asset. A Scene places the
canonical mesh by ``v_world = R · v_canonical + t``, so the body pose is

    position p = t + R · com,   orientation Q = R · A,

and back: ``R = Q · Aᵀ``, ``t = p − R · com``. Quaternions are pybullet's (x, y, z, w). All arrays are
batched over objects: t, p, com (N, 3); R, Q, A (N, 3, 3); q (N, 4).
"""

from __future__ import annotations

import numpy as np


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w) → (N, 3, 3) rotation matrices (normalised first)."""
    q = np.asarray(q, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations → (N, 4) quaternions (x, y, z, w); a slightly non-orthonormal R (float32 files)
    gives the quaternion of the nearest rotation."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, np.float64).reshape(-1, 3, 3)).as_quat()


def scene_to_body(t: np.ndarray, R: np.ndarray, com: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scene poses → body (COM) poses: (positions (N, 3), quaternions (N, 4)).

    ``R`` is first replaced by the exact rotation of its quaternion, so reading the body back returns
    ``t`` to round-off (and ``R`` to within its own non-orthonormality).
    """
    q = matrix_to_quat(np.asarray(R, np.float64) @ axes)
    R_exact = quat_to_matrix(q) @ np.swapaxes(axes, -1, -2)
    p = np.asarray(t, np.float64) + np.einsum("nij,nj->ni", R_exact, com)
    return p, q


def body_to_scene(p: np.ndarray, q: np.ndarray, com: np.ndarray, axes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body (COM) poses → Scene poses: (translation (N, 3) bbox centre, rotation (N, 3, 3) world-from-local)."""
    R = quat_to_matrix(q) @ np.swapaxes(axes, -1, -2)
    t = np.asarray(p, np.float64) - np.einsum("nij,nj->ni", R, com)
    return t, R
