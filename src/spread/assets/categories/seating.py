"""Beds and seats: bed, sofa, armchair, chair, stool, bench.

Build frame (metres, y-up, floor y = 0, front +z: the sitter faces +z, a bed's foot is at +z and its
headboard at −z). Seats are "seat" support surfaces (pillows, books, remotes go there); the mattress
top is a "bed" surface. Upholstered pieces use an effective density of ~200 kg/m³.
"""

from __future__ import annotations

import numpy as np

from spread.assets.categories.furniture_parts import board, corner_legs
from spread.assets.categories.registry import category
from spread.assets.primitives import JOIN, box_between, frustum, hull, post, prism, rounded_slab
from spread.assets.shape import Shape, disc_surface, rect_surface

WOOD = 600.0
UPHOLSTERED = 150.0


@category("bed", "furniture", UPHOLSTERED, ("bedroom",), ("platform", "legs", "footboard"))
def bed(rng, style):
    """Bed frame + mattress + headboard; single to king size, mattress top at 0.45–0.65 m."""
    width = float(rng.choice([0.95, 1.4, 1.6, 1.8])) + float(rng.uniform(-0.05, 0.05))
    length = float(rng.uniform(1.95, 2.15))
    frame_top = float(rng.uniform(0.22, 0.32))
    mattress_t = float(rng.uniform(0.2, 0.28))
    lift = float(rng.uniform(0.1, 0.15)) if style == "legs" else 0.0
    top = frame_top - JOIN + mattress_t
    parts = [
        box_between((-width / 2, lift, -length / 2), (width / 2, frame_top, length / 2)),
        rounded_slab((width - 0.04, mattress_t, length - 0.05), 0.06, (0.0, frame_top - JOIN + mattress_t / 2, 0.01)),
    ]
    head_h, head_t = float(rng.uniform(0.9, 1.2)), float(rng.uniform(0.05, 0.1))
    xw = width / 2 + 0.02  # head- and footboard stand 2 cm proud of the frame's sides
    parts.append(box_between((-xw, 0.0, -length / 2 - head_t), (xw, head_h, -length / 2 + 0.02)))
    if lift > 0:
        parts += corner_legs(width, length, lift, float(rng.uniform(0.05, 0.08)), 0.03)
    if style == "footboard":
        foot_h = top + float(rng.uniform(0.0, 0.12))
        parts.append(box_between((-xw, 0.0, length / 2 - 0.02), (xw, foot_h, length / 2 + 0.04)))
    z1 = length / 2 - 0.015 - (0.02 if style == "footboard" else 0.0)
    return Shape(parts, [rect_surface(top, -width / 2 + 0.02, -length / 2 + 0.035, width / 2 - 0.02, z1, 0.06,
                                      kind="bed")])


def _upholstered(rng, seat_width, style, cushions) -> Shape:
    """Sofa-like seat: base, back, two arms (unless armless), seat cushions, short legs or a skirt.

    ``seat_width`` is the width between the arms; the arms add 0.1–0.2 m each.
    """
    depth = float(rng.uniform(0.8, 0.95))
    seat_h = float(rng.uniform(0.42, 0.48))
    cushion_t = float(rng.uniform(0.1, 0.15))
    back_h, back_t = float(rng.uniform(0.75, 0.9)), float(rng.uniform(0.15, 0.25))
    arm_w = 0.0 if style == "armless" else float(rng.uniform(0.1, 0.2))
    arm_h = float(rng.uniform(0.55, 0.65))
    lift = float(rng.uniform(0.06, 0.12)) if style == "legs" else 0.0
    width = seat_width + 2 * arm_w
    xi = seat_width / 2  # inner face of the arms
    base_top = seat_h - cushion_t
    parts = [
        box_between((-xi - JOIN, lift, -depth / 2 + back_t - JOIN), (xi + JOIN, base_top + JOIN, depth / 2 - 0.01)),
        box_between((-xi - JOIN, lift, -depth / 2), (xi + JOIN, back_h, -depth / 2 + back_t)),
    ]
    if arm_w > 0:
        for x0, x1 in ((-width / 2, -xi), (xi, width / 2)):
            parts.append(rounded_slab((x1 - x0, arm_h - lift, depth), 0.04, ((x0 + x1) / 2, (lift + arm_h) / 2, 0.0)))
    cw = 2 * xi / cushions
    seat_d = depth / 2 - 0.01 - (-depth / 2 + back_t)
    for k in range(cushions):
        cx = -xi + cw * (k + 0.5)
        parts.append(rounded_slab((cw + JOIN, cushion_t + JOIN, seat_d), 0.04,
                                  (cx, base_top + (cushion_t + JOIN) / 2, -depth / 2 + back_t + seat_d / 2)))
    if lift > 0:
        parts += corner_legs(width - 0.04, depth - 0.04, lift, float(rng.uniform(0.04, 0.06)), 0.02, taper=0.7)
    surface = rect_surface(seat_h + JOIN, -xi, -depth / 2 + back_t, xi, depth / 2 - 0.01, 0.05, kind="seat")
    return Shape(parts, [surface])


@category("sofa", "furniture", UPHOLSTERED, ("living",), ("legs", "skirt", "armless"))
def sofa(rng, style):
    """Two- or three-seat sofa, 1.1–2.4 m wide, seat at 0.42–0.48 m."""
    cushions = int(rng.integers(2, 4))
    return _upholstered(rng, float(rng.uniform(0.55, 0.65)) * cushions, style, cushions)


@category("armchair", "furniture", UPHOLSTERED, ("living", "bedroom", "office"), ("legs", "skirt"))
def armchair(rng, style):
    """Single upholstered armchair, 0.75–0.95 m wide."""
    return _upholstered(rng, float(rng.uniform(0.52, 0.62)), style, 1)


@category("chair", "furniture", WOOD, ("dining", "office", "kitchen"), ("slats", "panel", "rails"))
def chair(rng, style):
    """Four-legged chair with a back, seat at 0.44–0.48 m."""
    width, depth = float(rng.uniform(0.4, 0.5)), float(rng.uniform(0.42, 0.52))
    seat_h, seat_t = float(rng.uniform(0.44, 0.48)), float(rng.uniform(0.03, 0.05))
    back_top = float(rng.uniform(0.8, 0.95))
    leg, inset = float(rng.uniform(0.03, 0.045)), float(rng.uniform(0.01, 0.02))
    parts = [board(width, depth, seat_h - seat_t, seat_t)]
    parts += corner_legs(width, depth, seat_h - seat_t, leg, inset, taper=float(rng.uniform(0.75, 1.0)),
                         splay=float(rng.uniform(0.0, 0.015)))
    xp, zp = width / 2 - inset - leg / 2, -depth / 2 + inset + leg / 2
    for sx in (-1, 1):
        parts.append(post((sx * xp, zp), (sx * xp, zp - 0.03), seat_h - JOIN, back_top, leg))
    z_top = zp - 0.03

    def back_piece(x0, x1, y0, y1, thick):
        """A board of the reclined back, following the posts' lean from (seat_h, zp) to (back_top, z_top)."""
        pts = []
        for y in (y0, y1):
            z = zp + (z_top - zp) * (y - seat_h) / (back_top - seat_h)
            pts += [(x, y, z + dz) for x in (x0, x1) for dz in (-thick / 2, thick / 2)]
        return hull(pts)

    if style == "panel":
        parts.append(back_piece(-xp, xp, seat_h + 0.1, back_top - 0.01, 0.02))
    else:
        rails = 1 if style == "slats" else int(rng.integers(2, 4))
        rail_h = float(rng.uniform(0.05, 0.1))
        for k in range(rails):
            y1 = back_top - 0.01 - k * (rail_h + 0.06)
            parts.append(back_piece(-xp, xp, y1 - rail_h, y1, 0.02))
        if style == "slats":
            for x in np.linspace(-xp, xp, 5)[1:-1]:
                parts.append(back_piece(x - 0.012, x + 0.012, seat_h - JOIN, y1 - rail_h + JOIN, 0.016))
    surface = rect_surface(seat_h, -width / 2, zp + leg / 2, width / 2, depth / 2, 0.04, kind="seat")
    return Shape(parts, [surface])


@category("stool", "furniture", WOOD, ("kitchen", "living"), ("four_legs", "three_legs", "bar_column"))
def stool(rng, style):
    """Round stool: 0.45–0.6 m, or a bar stool of 0.65–0.78 m on a column."""
    radius, seat_t = float(rng.uniform(0.15, 0.2)), float(rng.uniform(0.03, 0.045))
    if style == "bar_column":
        height = float(rng.uniform(0.65, 0.78))
        foot_r = radius * float(rng.uniform(1.0, 1.2))
        parts = [prism(radius, height - seat_t, height, 16), frustum(foot_r, foot_r * 0.7, 0.0, 0.03, 16),
                 prism(0.03, 0.03 - JOIN, height - seat_t + JOIN, 10)]
        return Shape(parts, [disc_surface(height, radius, 0.03, kind="seat")])
    height = float(rng.uniform(0.45, 0.6))
    parts = [prism(radius, height - seat_t, height, 16)]
    n = 4 if style == "four_legs" else 3
    leg = float(rng.uniform(0.03, 0.04))
    r_top, r_foot = radius * 0.65, radius * float(rng.uniform(0.8, 1.05))
    for k in range(n):
        a = 2 * np.pi * k / n + np.pi / n
        c, s = np.cos(a), np.sin(a)
        foot, top = (r_foot * c, r_foot * s), (r_top * c, r_top * s)
        parts.append(post(foot, top, 0.0, height - seat_t + JOIN, leg * 0.8, leg))
    return Shape(parts, [disc_surface(height, radius, 0.03, kind="seat")])


@category("bench", "furniture", WOOD, ("living", "dining"), ("four_legs", "panel_legs"))
def bench(rng, style):
    """Backless bench, 1.0–1.6 m long, seat at 0.42–0.48 m."""
    width, depth = float(rng.uniform(1.0, 1.6)), float(rng.uniform(0.3, 0.4))
    height, seat_t = float(rng.uniform(0.42, 0.48)), float(rng.uniform(0.03, 0.05))
    parts = [board(width, depth, height - seat_t, seat_t)]
    if style == "four_legs":
        parts += corner_legs(width, depth, height - seat_t, float(rng.uniform(0.04, 0.06)), 0.04)
    else:
        x = width / 2 - float(rng.uniform(0.08, 0.15))
        for x0 in (-x, x - 0.04):
            z = depth / 2 - 0.02
            parts.append(box_between((x0, 0.0, -z), (x0 + 0.04, height - seat_t + JOIN, z)))
    return Shape(parts, [rect_surface(height, -width / 2, -depth / 2, width / 2, depth / 2, 0.04, kind="seat")])
