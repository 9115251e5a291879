"""Convex building blocks for procedural assets (trimesh meshes, metres, y-up).

Every function returns convex parts; an asset is a list of them (the physics collision shapes) and its
visual mesh is their boolean union. Two rules keep that union watertight:

* parts that join **overlap** a little (:data:`JOIN`), they never just touch along a face, edge or
  corner computed in two different ways;
* parts of one ring (walls of a bowl, a base under it) take their corner points from one shared
  angle table (:func:`ring`), so faces that coincide coincide *exactly*, bit for bit.

Round things are polygons: an ``n``-sided ring has vertices at angles ``phase + 2πk/n`` about the
vertical axis (x = r·cos, z = r·sin). The default phase ``π/n`` puts a flat face towards +x (and
towards ±z when ``n`` is a multiple of 4), so a prism lying on its side rests on a face.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import trimesh

#: Overlap (metres) between parts that are joined, so their union has no touching-only contacts.
JOIN = 1e-3


def hull(points) -> trimesh.Trimesh:
    """Convex hull of a point set (n, 3)."""
    return trimesh.convex.convex_hull(np.asarray(points, np.float64))


_UNIT_BOX = trimesh.creation.box()  # vertices at ±0.5, outward faces


def box_between(lo, hi) -> trimesh.Trimesh:
    """Axis-aligned box spanning the corners ``lo`` and ``hi`` exactly (no rounding of the corners)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    vertices = np.where(_UNIT_BOX.vertices > 0, hi, lo)
    return trimesh.Trimesh(vertices, _UNIT_BOX.faces.copy(), process=False)


def box(size, centre=(0.0, 0.0, 0.0)) -> trimesh.Trimesh:
    """Axis-aligned box of ``size`` (x, y, z) centred at ``centre``."""
    size, centre = np.asarray(size, float), np.asarray(centre, float)
    return box_between(centre - size / 2, centre + size / 2)


def ring(sides: int, phase: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(cos, sin) of the ring angles ``phase + 2πk/sides``; default phase ``π/sides``."""
    phase = np.pi / sides if phase is None else phase
    a = phase + 2 * np.pi * np.arange(sides) / sides
    return np.cos(a), np.sin(a)


def _circle(radius: float, y: float, sides: int, centre_xz=(0.0, 0.0), phase=None) -> np.ndarray:
    c, s = ring(sides, phase)
    return np.stack([centre_xz[0] + radius * c, np.full(sides, float(y)), centre_xz[1] + radius * s], 1)


def frustum(r0: float, r1: float, y0: float, y1: float, sides: int = 16, centre_xz=(0.0, 0.0),
            phase=None) -> trimesh.Trimesh:
    """Vertical truncated cone: radius ``r0`` at ``y0``, ``r1`` at ``y1`` (an apex where a radius is 0)."""
    pts = []
    for r, y in ((r0, y0), (r1, y1)):
        pts.append(_circle(r, y, sides, centre_xz, phase) if r > 0 else [[centre_xz[0], y, centre_xz[1]]])
    return hull(np.concatenate(pts))


def prism(radius: float, y0: float, y1: float, sides: int = 16, centre_xz=(0.0, 0.0), phase=None):
    """Vertical regular prism (a polygonal cylinder) from ``y0`` to ``y1``."""
    return frustum(radius, radius, y0, y1, sides, centre_xz, phase)


def lathe(profile: Sequence[tuple[float, float]], sides: int = 16, centre_xz=(0.0, 0.0)) -> list:
    """Solid of revolution as a stack of frusta, one per band of ``profile`` [(y, r), ...], y rising."""
    return [frustum(r0, r1, y0, y1, sides, centre_xz) for (y0, r0), (y1, r1) in zip(profile, profile[1:])]


def shell(profile: Sequence[tuple[float, float, float]], sides: int = 12, centre_xz=(0.0, 0.0)) -> list:
    """Open thin wall of revolution: ``profile`` [(y, r_inner, r_outer), ...] with y rising.

    Each band between two profile rows is cut into ``sides`` convex segments, each the hull of its
    inner and outer arc points, so the inside stays hollow. Segments share their side faces exactly.
    """
    c, s = ring(sides)
    parts = []
    for (y0, a0, b0), (y1, a1, b1) in zip(profile, profile[1:]):
        for k in range(sides):
            pts = [(centre_xz[0] + r * c[j], y, centre_xz[1] + r * s[j])
                   for j in (k, (k + 1) % sides) for r, y in ((a0, y0), (b0, y0), (a1, y1), (b1, y1))]
            parts.append(hull(pts))
    return parts


def horizontal_prism(radius: float, length: float, centre, axis: str = "x", sides: int = 12) -> trimesh.Trimesh:
    """Prism with its axis along world x or z, centred at ``centre``; a flat face looks down (−y)."""
    c, s = ring(sides, phase=np.pi / 2 + np.pi / sides)  # a face normal along −y (and +y when even)
    u, v = radius * c, radius * s  # v is the vertical offset, u the horizontal one across the axis
    pts = []
    for t in (-length / 2, length / 2):
        for ui, vi in zip(u, v):
            pts.append((t, vi, ui) if axis == "x" else (ui, vi, t))
    return hull(np.asarray(pts) + np.asarray(centre, float))


def rounded_slab(size, radius: float, centre=(0.0, 0.0, 0.0), corner_sides: int = 3) -> trimesh.Trimesh:
    """Box of ``size`` (x, y, z) whose four vertical edges are rounded with ``radius`` (phones, boards)."""
    sx, sy, sz = np.asarray(size, float) / 2
    radius = min(radius, sx, sz)
    pts = []
    for cx, cz, a0 in ((sx, sz, 0.0), (-sx, sz, 90.0), (-sx, -sz, 180.0), (sx, -sz, 270.0)):
        for a in np.radians(a0 + np.linspace(0, 90, corner_sides + 1)):
            x = np.sign(cx) * (sx - radius) + radius * np.cos(a)
            z = np.sign(cz) * (sz - radius) + radius * np.sin(a)
            pts += [(x, -sy, z), (x, sy, z)]
    return hull(np.asarray(pts) + np.asarray(centre, float))


def ellipsoid(radii, centre=(0.0, 0.0, 0.0), rings: int = 7, sides: int = 14, cut_below: float | None = None,
              squareness: float = 1.0) -> trimesh.Trimesh:
    """Polyhedral (super)ellipsoid with semi-axes ``radii``; ``cut_below`` flattens it at that local y.

    ``squareness`` > 1 makes it boxier (pillows, cushions); 1 is an ellipsoid.
    """
    rx, ry, rz = radii
    e = 1.0 / squareness
    lat = np.linspace(-np.pi / 2, np.pi / 2, rings + 2)[1:-1]
    lon = 2 * np.pi * np.arange(sides) / sides

    def sp(t):  # signed power: the superellipse map
        return np.sign(t) * np.abs(t) ** e

    pts = [(0.0, -ry, 0.0), (0.0, ry, 0.0)]
    for p in lat:
        for q in lon:
            pts.append((rx * sp(np.cos(p)) * sp(np.cos(q)), ry * sp(np.sin(p)), rz * sp(np.cos(p)) * sp(np.sin(q))))
    pts = np.asarray(pts)
    if cut_below is not None:
        pts[:, 1] = np.maximum(pts[:, 1], cut_below)
    return hull(pts + np.asarray(centre, float))


def strut(p0, p1, width: float, depth: float | None = None) -> trimesh.Trimesh:
    """Square-section bar from ``p0`` to ``p1`` (slanted legs, kickstands, handles)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = (p1 - p0) / np.linalg.norm(p1 - p0)
    ref = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, ref)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    hw, hd = width / 2, (depth if depth is not None else width) / 2
    pts = [p + a * hw * u + b * hd * v for p in (p0, p1) for a in (-1, 1) for b in (-1, 1)]
    return hull(pts)


def rim(size_x: float, size_z: float, wall: float, y0: float, y1: float, centre_xz=(0.0, 0.0)) -> list:
    """Four boxes forming a rectangular rim (tray, basket, drawer): outer size ``size_x × size_z``.

    The x-walls run the full length; the z-walls sit between them, overlapping by :data:`JOIN`.
    """
    xa, xb = centre_xz[0] - size_x / 2, centre_xz[0] + size_x / 2
    za, zb = centre_xz[1] - size_z / 2, centre_xz[1] + size_z / 2
    return [
        box_between((xa, y0, zb - wall), (xb, y1, zb)),
        box_between((xa, y0, za), (xb, y1, za + wall)),
        box_between((xb - wall, y0, za + wall - JOIN), (xb, y1, zb - wall + JOIN)),
        box_between((xa, y0, za + wall - JOIN), (xa + wall, y1, zb - wall + JOIN)),
    ]


def c_handle(x_low: float, x_high: float, y0: float, y1: float, reach: float, thickness: float, width: float,
             z: float = 0.0, dig: float = 0.003) -> list:
    """A "[" shaped handle of three bars on the +x side of a body.

    The bottom bar (at ``y0``) starts ``dig`` metres inside the wall face at ``x_low``, the top bar
    (ending at ``y1``) inside the face at ``x_high``; both reach ``reach`` beyond the outer face and
    a vertical bar joins their ends.
    """
    x1 = max(x_low, x_high) + reach
    t, hw = thickness, width / 2
    return [
        box_between((x_high - dig, y1 - t, z - hw), (x1, y1, z + hw)),
        box_between((x_low - dig, y0, z - hw), (x1, y0 + t, z + hw)),
        box_between((x1 - t, y0 + t - JOIN, z - hw), (x1, y1 - t + JOIN, z + hw)),
    ]


def post(bottom_xz, top_xz, y0: float, y1: float, w0: float, w1: float | None = None) -> trimesh.Trimesh:
    """Leg with horizontal square ends: side ``w0`` at ``y0`` centred on ``bottom_xz``, ``w1`` at ``y1``.

    Straight, tapered or splayed (when the centres differ); its foot is flat on y = ``y0``.
    """
    w1 = w0 if w1 is None else w1
    pts = [(cx + a * w / 2, y, cz + b * w / 2)
           for (cx, cz), y, w in ((bottom_xz, y0, w0), (top_xz, y1, w1)) for a in (-1, 1) for b in (-1, 1)]
    return hull(pts)
