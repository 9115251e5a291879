"""What a category generator returns, and the rest-pose rotations generators ask for.

A generator builds one variant in its own *build frame*: metres, y-up, standing on y = 0, width
along x, depth along z, **front towards +z** (a sofa's back, a bookcase's back panel, a bed's headboard
are at −z). The builder later moves everything into the canonical frame (bbox centre at the origin).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from spread.assets.library import SupportSurface


@dataclass
class Shape:
    """One variant's geometry: convex ``parts`` plus where things go on it and how it can lie.

    ``surfaces`` are support surfaces in the build frame; ``rest_poses`` map a name to a candidate
    world-from-local rotation (validated for stability by the builder, unstable ones are dropped);
    ``rest_weights`` give their relative sampling weights; ``tags`` are added to the category's tags.
    """

    parts: list
    surfaces: list[SupportSurface] = field(default_factory=list)
    rest_poses: dict[str, np.ndarray] = field(default_factory=lambda: {"upright": np.eye(3)})
    rest_weights: dict[str, float] = field(default_factory=dict)
    tags: list[str] = field(default_factory=list)


def rot_x(deg: float) -> np.ndarray:
    """Rotation about +x by ``deg`` degrees (right-handed)."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], float).round(15)


def rot_z(deg: float) -> np.ndarray:
    """Rotation about +z by ``deg`` degrees (right-handed)."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], float).round(15)


#: Local +x face down, local y axis horizontal: a bottle or can lying on its side.
LIE_ON_SIDE = rot_z(-90.0)
#: The canonical pose of things that lie (phones, books, laptops), named "flat".
FLAT = {"flat": np.eye(3)}
#: Local +z face down: a book standing on its bottom edge.
STAND_ON_EDGE = rot_x(90.0)


def rect_surface(height: float, x0: float, z0: float, x1: float, z1: float, inset: float,
                 clearance: float = float("inf"), kind: str = "top") -> SupportSurface:
    """Support rectangle ``[x0, x1] × [z0, z1]`` at ``height``, shrunk by ``inset`` on every side."""
    inset = min(inset, 0.45 * (x1 - x0), 0.45 * (z1 - z0))
    return SupportSurface(height=float(height), xz_min=(x0 + inset, z0 + inset), xz_max=(x1 - inset, z1 - inset),
                          clearance=float(clearance), kind=kind)


def disc_surface(height: float, radius: float, inset: float, clearance: float = float("inf"),
                 kind: str = "top", centre_xz=(0.0, 0.0)) -> SupportSurface:
    """The square inscribed in a disc of ``radius`` (less ``inset``), at ``height``."""
    h = max(radius / np.sqrt(2) - inset, 0.3 * radius)
    cx, cz = centre_xz
    return SupportSurface(height=float(height), xz_min=(cx - h, cz - h), xz_max=(cx + h, cz + h),
                          clearance=float(clearance), kind=kind)
