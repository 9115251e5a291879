"""A pinhole camera for the 3D views: where it stands, what it sees, and a default that frames a room.

Frames and units (DESIGN §3): world y-up, metres, floor y = 0. Matrices are OpenGL's (camera looks down
its −z, +y up on the image, clip space to NDC by the perspective divide) and are handed to renderers as
16 floats in column-major order, as pybullet's ``getCameraImage`` takes them.

**Default view** (:func:`fit_camera`): a three-quarter view from above. ``azimuth`` 0 puts the camera on
the room's +z side looking towards −z, so +x is to the right and +z comes towards the viewer — the same
orientation as the top-down renders (:mod:`spread.render.settings`: +x right, +z down the image), tilted
by ``elevation`` degrees above the horizon and turned by ``azimuth`` degrees about +y (positive: the camera
moves towards +x). The camera looks at the centre of the box to frame and stands back exactly as far as
needed for all eight corners of that box to fall inside the image (with ``margin`` around them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np


@dataclass(frozen=True)
class Camera:
    """eye, target: world points (metres); up: world up hint; fov_y: vertical field of view, degrees;
    aspect: width / height; near, far: clip distances, metres; shift, zoom: a lens shift and zoom of the
    image plane (normalised device coordinates become ``zoom · (ndc − shift)``), which frame a box exactly
    without turning the camera."""

    eye: tuple[float, float, float]
    target: tuple[float, float, float]
    fov_y: float
    aspect: float
    near: float
    far: float
    up: tuple[float, float, float] = (0.0, 1.0, 0.0)
    shift: tuple[float, float] = (0.0, 0.0)
    zoom: float = 1.0

    def axes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(right, up, forward) unit vectors in the world; forward points from the eye to the target."""
        eye, target = np.asarray(self.eye, float), np.asarray(self.target, float)
        forward = target - eye
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, np.asarray(self.up, float))
        if np.linalg.norm(right) < 1e-9:
            raise ValueError(f"camera looks along its up vector {self.up}: no image orientation")
        right /= np.linalg.norm(right)
        return right, np.cross(right, forward), forward

    def view(self) -> np.ndarray:
        """(4, 4) world → camera matrix (OpenGL: camera looks down −z)."""
        right, up, forward = self.axes()
        eye = np.asarray(self.eye, float)
        m = np.eye(4)
        m[0, :3], m[1, :3], m[2, :3] = right, up, -forward
        m[:3, 3] = -m[:3, :3] @ eye
        return m

    def projection(self) -> np.ndarray:
        """(4, 4) camera → clip matrix (OpenGL perspective)."""
        f = 1.0 / math.tan(math.radians(self.fov_y) / 2)
        n, fa = self.near, self.far
        m = np.zeros((4, 4))
        m[0, 0], m[1, 1] = f / self.aspect, f
        m[2, 2], m[2, 3] = (fa + n) / (n - fa), 2 * fa * n / (n - fa)
        m[3, 2] = -1.0
        for axis in (0, 1):  # ndc' = zoom · (ndc − shift), i.e. clip' = zoom · (clip − shift · w)
            m[axis] = self.zoom * (m[axis] - self.shift[axis] * m[3])
        return m

    def gl_matrices(self) -> tuple[list[float], list[float]]:
        """(view, projection) as 16 floats each, column-major (pybullet's ``getCameraImage`` arguments)."""
        return self.view().T.reshape(-1).tolist(), self.projection().T.reshape(-1).tolist()

    def project(self, points: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """World points (P, 3) → (pixel (column, row) (P, 2) with row 0 at the top, depth along the view (P,))."""
        p = np.concatenate([np.asarray(points, float), np.ones((len(points), 1))], axis=1)
        cam = p @ self.view().T
        clip = cam @ self.projection().T
        ndc = clip[:, :2] / clip[:, 3:4]
        cols = (ndc[:, 0] + 1) / 2 * width
        rows = (1 - ndc[:, 1]) / 2 * height
        return np.stack([cols, rows], axis=1), -cam[:, 2]


def box_corners(lo, hi) -> np.ndarray:
    """(8, 3) corners of the axis-aligned box [lo, hi]."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def fit_camera(lo, hi, aspect: float, fov_y: float = 40.0, elevation: float = 40.0, azimuth: float = 30.0,
               margin: float = 0.04) -> Camera:
    """The module docstring's default view of the world box [lo, hi] (metres).

    ``elevation`` (degrees above the horizon, in (0, 90)), ``azimuth`` (degrees about +y from the +z side),
    ``margin``: share of the image's half-size left free around the box on the tighter side.
    """
    if not 0 < elevation < 90:
        raise ValueError(f"elevation must be in (0, 90) degrees, got {elevation}")
    if not 0 < fov_y < 180 or not aspect > 0:
        raise ValueError(f"fov_y must be in (0, 180) degrees and aspect > 0, got {fov_y}, {aspect}")
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()) \
            or (hi < lo).any():
        raise ValueError(f"fit_camera: need finite box corners lo <= hi, got {lo}, {hi}")
    target = (lo + hi) / 2
    el, az = math.radians(elevation), math.radians(azimuth)
    back = np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])  # target → eye
    probe = Camera(tuple(target + back), tuple(target), fov_y, aspect, 0.01, 100.0)
    right, up, forward = probe.axes()
    ty = math.tan(math.radians(fov_y) / 2) * (1 - margin)
    tx = ty * aspect
    rel = box_corners(lo, hi) - target
    x, y, depth = rel @ right, rel @ up, rel @ forward
    # a corner at lateral offset x and depth offset `depth` is inside when |x| <= tx · (distance + depth)
    distance = float(np.max(np.maximum(np.abs(x) / tx, np.abs(y) / ty) - depth))
    distance = max(distance, float(np.max(np.abs(depth))) + 0.05, 0.1)
    radius = float(np.linalg.norm(hi - lo)) / 2
    eye = target + distance * back
    camera = Camera(tuple(eye), tuple(target), fov_y, aspect, near=max(0.01, (distance - radius) * 0.5),
                    far=distance + 2 * radius + 1.0)
    pixels, _ = camera.project(box_corners(lo, hi), 2, 2)  # a 2 × 2 image: ndc = (col − 1, 1 − row)
    ndc = np.stack([pixels[:, 0] - 1, 1 - pixels[:, 1]], axis=1)
    low, high = ndc.min(0), ndc.max(0)
    half = np.maximum((high - low) / 2, 1e-6)
    return replace(camera, shift=tuple(float(v) for v in (low + high) / 2), zoom=float((1 - margin) / half.max()))
