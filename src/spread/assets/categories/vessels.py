"""Open hollow vessels (cups, bowls, pots, vases) as a floor plus a ring of convex wall segments.

Build frame: metres, y-up, the vessel standing on y = ``y0`` with its axis on the y axis. The outer
profile is a list of (y, r_outer) rows from the bottom (y = 0 relative) to the rim; the wall is
``wall`` thick horizontally and the floor ``floor`` thick. Because every segment is the hull of its
own inner and outer arc points, the inside is really hollow and the parts are the exact collision
shapes. A handle is attached on the +x side, where a flat wall face looks along +x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spread.assets.primitives import c_handle, frustum, shell


@dataclass
class Vessel:
    """The vessel's parts and what placement needs: inner floor height/radius, rim height."""

    parts: list
    floor_height: float  # y of the inner floor's top
    floor_radius: float  # apothem of the inner wall at the floor's top
    rim_height: float
    sides: int

    def apothem_at(self, profile, y: float) -> float:
        """Outer wall's distance from the axis to a flat face at height ``y`` (for attachments)."""
        return float(np.interp(y, [p[0] for p in profile], [p[1] for p in profile])) * np.cos(np.pi / self.sides)


def vessel(profile, wall: float, floor: float, sides: int = 12, y0: float = 0.0) -> Vessel:
    """Floor + wall segments for the outer ``profile`` [(y, r), ...] (y relative to ``y0``, rising)."""
    ys = np.array([p[0] for p in profile], float)
    rs = np.array([p[1] for p in profile], float)
    rows = [(y0 + y, r - wall, r) for y, r in zip(ys, rs)]
    parts = shell(rows, sides)
    # the floor reaches halfway into the wall at its bottom and top, so it joins the wall everywhere
    r_bottom = rs[0] - wall / 2
    r_top = float(np.interp(floor, ys, rs)) - wall / 2
    parts.insert(0, frustum(r_bottom, r_top, y0 + ys[0], y0 + floor, sides))
    inner = (r_top - wall / 2) * np.cos(np.pi / sides)
    return Vessel(parts, y0 + floor, float(inner), float(y0 + ys[-1]), sides)


def add_side_handle(v: Vessel, profile, y_low: float, y_high: float, reach: float, thickness: float,
                    width: float) -> None:
    """Attach a "[" handle on +x between heights ``y_low`` and ``y_high`` (relative to the floor y0=0)."""
    x_low = v.apothem_at(profile, y_low + thickness / 2)
    x_high = v.apothem_at(profile, y_high - thickness / 2)
    v.parts += c_handle(x_low, x_high, y_low, y_high, reach, thickness, width)
