"""Small everyday things: book, pencil, fruit, toy.

Build frame (metres, y-up, resting on y = 0). Books lie flat (cover up, spine on −x, height along
z) and may also stand on their bottom edge; fruit is polyhedral with a flattened underside, so it
rests on a face instead of rolling.
"""

from __future__ import annotations

import numpy as np

from spread.assets.categories.registry import category
from spread.assets.primitives import JOIN, box, box_between, ellipsoid, horizontal_prism, hull, prism
from spread.assets.shape import FLAT, STAND_ON_EDGE, Shape, rect_surface


@category("book", "object", 700.0, ("office", "living", "bedroom", "stackable"), ("paperback", "hardcover", "large"))
def book(rng, style):
    """Book lying flat: a page block between two covers joined by a spine on −x."""
    lo, hi = {"paperback": ([0.105, 0.012, 0.17], [0.13, 0.035, 0.2]),
              "hardcover": ([0.14, 0.02, 0.21], [0.18, 0.05, 0.26]),
              "large": ([0.22, 0.015, 0.27], [0.3, 0.035, 0.33])}[style]
    w, t, h = (float(v) for v in rng.uniform(lo, hi))
    c = 0.0015 if style == "paperback" else 0.003  # cover thickness
    o = 0.0 if style == "paperback" else 0.003  # cover overhang beyond the pages
    parts = [
        box_between((-w / 2, 0.0, -h / 2), (w / 2, c, h / 2)),
        box_between((-w / 2, t - c, -h / 2), (w / 2, t, h / 2)),
        box_between((-w / 2, 0.0, -h / 2), (-w / 2 + c, t, h / 2)),
        box_between((-w / 2 + c - JOIN, c - JOIN, -h / 2 + o), (w / 2 - o, t - c + JOIN, h / 2 - o)),
    ]
    poses = {"flat": np.eye(3), "upright": STAND_ON_EDGE}
    return Shape(parts, [rect_surface(t, -w / 2, -h / 2, w / 2, h / 2, 0.01)], poses, {"flat": 0.8, "upright": 0.2})


@category("pencil", "object", 700.0, ("office",), ("hex", "octagonal", "marker"))
def pencil(rng, style):
    """Pencil or marker lying on a face of its polygonal barrel, axis along x, tip at +x."""
    sides = 6 if style == "hex" else 8
    r = float(rng.uniform(0.007, 0.009) if style == "marker" else rng.uniform(0.0035, 0.0045))
    length = float(rng.uniform(0.11, 0.14) if style == "marker" else rng.uniform(0.14, 0.19))
    tip = float(rng.uniform(0.015, 0.025))
    y = r * np.cos(np.pi / sides)  # the axis height when lying on a face
    barrel = horizontal_prism(r, length, (0.0, y, 0.0), "x", sides)
    ring = barrel.vertices[barrel.vertices[:, 0] > 0]
    cone = hull(np.vstack([ring - [JOIN, 0, 0], [[length / 2 + tip, y, 0.0]]]))
    if style == "marker":  # a cap a little wider than the barrel, also resting on its face
        end = horizontal_prism(r * 1.05, 0.04, (-length / 2 + 0.005, r * 1.05 * np.cos(np.pi / sides), 0.0), "x", sides)
    else:  # an eraser a little narrower than the barrel
        end = horizontal_prism(r * 0.9, 0.02, (-length / 2 + 0.005, y, 0.0), "x", sides)
    return Shape([barrel, cone, end], rest_poses=FLAT)


@category("fruit", "object", 900.0, ("food", "kitchen"), ("apple", "orange", "pear"))
def fruit(rng, style):
    """Apple, orange or pear: polyhedral, flattened underneath so it rests on a face."""
    if style == "orange":
        r = float(rng.uniform(0.035, 0.045))
        return Shape([ellipsoid((r, r * 0.95, r), (0, 0, 0), rings=6, sides=12, cut_below=-0.8 * r)])
    if style == "apple":
        r = float(rng.uniform(0.035, 0.045))
        body = ellipsoid((r, r * 0.9, r), (0, 0, 0), rings=6, sides=12, cut_below=-0.75 * r)
        return Shape([body, prism(0.0025, r * 0.8, r * 0.9 + 0.012, 6)])
    r = float(rng.uniform(0.03, 0.038))
    body = ellipsoid((r, r * 0.9, r), (0, 0, 0), rings=5, sides=12, cut_below=-0.75 * r)
    neck = ellipsoid((r * 0.6, r * 0.9, r * 0.6), (0, r * 0.9, 0), rings=5, sides=10)
    return Shape([body, neck, prism(0.0025, r * 1.6, r * 1.8 + 0.012, 6)])


@category("toy", "object", 600.0, ("toy", "living", "bedroom"), ("block", "car", "tower"))
def toy(rng, style):
    """Wooden toy: a block, a little car on four polygonal wheels, or a tower of blocks."""
    if style == "block":
        s = float(rng.uniform(0.03, 0.06))
        return Shape([box((s, s, s), (0.0, s / 2, 0.0))])
    if style == "tower":
        parts, y = [], 0.0
        for k in range(int(rng.integers(2, 4))):
            s = float(rng.uniform(0.03, 0.05)) * (1.0 - 0.15 * k)
            dx, dz = (float(v) for v in rng.uniform(-0.003, 0.003, 2))
            parts.append(box((s, s, s), (dx, y + s / 2 - (JOIN if k else 0.0), dz)))
            y += s - (JOIN if k else 0.0)
        return Shape(parts)
    length, width = float(rng.uniform(0.08, 0.15)), float(rng.uniform(0.04, 0.07))
    wheel_r, wheel_w = float(rng.uniform(0.01, 0.016)), 0.01
    y_axle = wheel_r * np.cos(np.pi / 8)
    body_h = float(rng.uniform(0.02, 0.03))
    body_z = width / 2 - wheel_w
    parts = [box_between((-length / 2, y_axle - 0.004, -body_z), (length / 2, y_axle + body_h, body_z))]
    cab = float(rng.uniform(0.4, 0.6)) * length
    top = y_axle + body_h
    cab_xy = ((-cab / 2, top - JOIN), (cab / 2, top - JOIN), (-0.35 * cab, top + body_h), (0.3 * cab, top + body_h))
    parts.append(hull([(x, y, z) for x, y in cab_xy for z in (-body_z + 0.004, body_z - 0.004)]))
    for sx in (-1, 1):
        for sz in (-1, 1):
            centre = (sx * (length / 2 - wheel_r - 0.005), y_axle, sz * (width / 2 - wheel_w / 2))
            parts.append(horizontal_prism(wheel_r, wheel_w + 2 * JOIN, centre, "z", 8))
    return Shape(parts)
