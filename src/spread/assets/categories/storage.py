"""Storage furniture: shelf, bookcase, nightstand, tv_stand, dresser, wardrobe.

Build frame (metres, y-up, floor y = 0, front +z, back panel at −z). Shelving units are real open
boards with gaps between them: every board's top is a support surface ("shelf", with the clearance
up to the underside of the board above; the top board is a "top" with no limit).
"""

from __future__ import annotations

import numpy as np

from spread.assets.categories.furniture_parts import board, drawer_fronts, plinth_or_legs
from spread.assets.categories.registry import category
from spread.assets.primitives import JOIN, box_between
from spread.assets.shape import Shape, rect_surface

WOOD = 600.0
#: Closed cabinets are mostly air: effective density of their solid carcass box.
CABINET = 150.0


def shelving(rng, width: float, depth: float, height: float, boards: int, back: bool, posts: bool,
             lift: float = 0.0) -> Shape:
    """Open shelving: two side panels (or four corner posts), ``boards`` boards, optional back panel.

    The lowest board's underside is at ``lift``; the top board's top face at ``height``. Boards stop
    1 cm short of the front; side panels stop 1 cm below the overhanging top.
    """
    t = float(rng.uniform(0.018, 0.025))
    side = float(rng.uniform(0.018, 0.025)) if not posts else float(rng.uniform(0.025, 0.035))
    back_t = 0.008 if back else 0.0
    xi = width / 2 - 0.01 - side  # inner face of the side panels / posts
    z_back, z_front = -depth / 2 + 0.005 + back_t, depth / 2 - 0.01
    parts = []
    x_spans = ((-xi - side, -xi), (xi, xi + side))  # the two sides, outer faces 1 cm inside the top
    z_spans = ((-depth / 2, -depth / 2 + side), (depth / 2 - side, depth / 2)) if posts else ((-depth / 2, depth / 2),)
    for x0, x1 in x_spans:
        for z0, z1 in z_spans:
            parts.append(box_between((x0, 0.0, z0), (x1, height - t + JOIN, z1)))
    if back:
        parts.append(box_between((-xi - JOIN, lift, -depth / 2 + 0.005), (xi + JOIN, height - t + JOIN, z_back)))
    # board undersides: evenly spaced with a little jitter, the top one at height - t
    gaps = rng.uniform(0.85, 1.15, boards - 1)
    gaps = gaps / gaps.sum() * (height - t - lift)
    y_under = np.concatenate([[lift], lift + np.cumsum(gaps)])
    y_under[-1] = height - t
    if posts:  # boards reach into the middle of the posts
        bx, zb, z_front = xi + side / 2, -depth / 2 + side / 2, depth / 2 - side / 2
    else:  # boards reach into the side panels (and the back panel)
        bx, zb = xi + JOIN, (z_back - JOIN if back else -depth / 2 + 0.01)
    surfaces = []
    for k, y in enumerate(y_under):
        if k == boards - 1:  # top board overhangs the sides by 1 cm and covers them
            parts.append(box_between((-width / 2, y, -depth / 2), (width / 2, height, depth / 2)))
            surfaces.append(rect_surface(height, -width / 2, -depth / 2, width / 2, depth / 2, 0.03))
        else:
            parts.append(box_between((-bx, y, zb), (bx, y + t, z_front)))
            surfaces.append(rect_surface(y + t, -xi, zb, xi, z_front, 0.02,
                                         clearance=float(y_under[k + 1] - (y + t)), kind="shelf"))
    if lift > 0:  # plinth under the bottom board
        parts.append(box_between((-xi - JOIN, 0.0, zb), (xi + JOIN, lift + JOIN, z_front - 0.02)))
    return Shape(parts, surfaces)


@category("shelf", "furniture", WOOD, ("living", "kitchen", "office"), ("open", "backed", "posts"))
def shelf(rng, style):
    """Open shelving unit with 3–5 boards, 0.8–1.8 m tall."""
    boards = int(rng.integers(3, 6))
    height = float(rng.uniform(0.8, 1.8))
    height = max(height, 0.3 * boards)
    return shelving(rng, float(rng.uniform(0.6, 1.2)), float(rng.uniform(0.25, 0.4)), height, boards,
                    back=style == "backed", posts=style == "posts", lift=float(rng.uniform(0.0, 0.06)))


@category("bookcase", "furniture", WOOD, ("living", "office", "bedroom"), ("plinth", "flush", "wide"))
def bookcase(rng, style):
    """Bookcase with a back panel and 4–6 boards, 1.2–2.0 m tall."""
    boards = int(rng.integers(4, 7))
    height = max(float(rng.uniform(1.2, 2.0)), 0.3 * boards)
    width = float(rng.uniform(0.9, 1.2) if style == "wide" else rng.uniform(0.6, 0.9))
    lift = float(rng.uniform(0.06, 0.1)) if style == "plinth" else 0.0
    return shelving(rng, width, float(rng.uniform(0.28, 0.38)), height, boards, back=True, posts=False, lift=lift)


def _cabinet(rng, width, depth, height, rows, cols, legs: bool, open_top_cubby: bool = False) -> Shape:
    """Carcass box with a top, drawer/door fronts, on a plinth or short legs; its top is a surface."""
    lift = float(rng.uniform(0.08, 0.15)) if legs else float(rng.uniform(0.04, 0.08))
    top_t = float(rng.uniform(0.02, 0.03))
    body_top = height - top_t
    z_front = depth / 2 - 0.015
    parts = [
        board(width, depth, body_top, top_t),
        box_between((-width / 2 + 0.01, lift, -depth / 2 + 0.005), (width / 2 - 0.01, body_top + JOIN, z_front)),
    ] + plinth_or_legs(rng, width - 0.02, depth - 0.03, lift + JOIN, legs)
    surfaces = [rect_surface(height, -width / 2, -depth / 2, width / 2, depth / 2, 0.03)]
    y_fronts_top = body_top
    if open_top_cubby:  # an open niche under the top: its floor is a shelf surface
        niche_h = float(rng.uniform(0.14, 0.2))
        y_floor = body_top - niche_h
        xi = width / 2 - 0.03
        parts[1] = box_between((-width / 2 + 0.01, lift, -depth / 2 + 0.005), (width / 2 - 0.01, y_floor, z_front))
        parts += [
            box_between((-width / 2 + 0.01, y_floor - JOIN, -depth / 2 + 0.005), (-xi, body_top + JOIN, z_front)),
            box_between((xi, y_floor - JOIN, -depth / 2 + 0.005), (width / 2 - 0.01, body_top + JOIN, z_front)),
            box_between((-xi - JOIN, y_floor - JOIN, -depth / 2 + 0.005),
                        (xi + JOIN, body_top + JOIN, -depth / 2 + 0.025)),
        ]
        surfaces.append(rect_surface(y_floor, -xi, -depth / 2 + 0.025, xi, z_front, 0.02,
                                     clearance=niche_h, kind="shelf"))
        y_fronts_top = y_floor
    parts += drawer_fronts(width - 0.03, lift, y_fronts_top, z_front, rows, cols)
    return Shape(parts, surfaces)


@category("nightstand", "furniture", CABINET, ("bedroom",), ("drawers", "open_niche", "legs"))
def nightstand(rng, style):
    """Bedside cabinet, top at 0.5–0.65 m."""
    width, depth, height = float(rng.uniform(0.4, 0.55)), float(rng.uniform(0.35, 0.45)), float(rng.uniform(0.5, 0.65))
    rows = 1 if style == "open_niche" else int(rng.integers(1, 3))
    return _cabinet(rng, width, depth, height, rows, 1, legs=style == "legs", open_top_cubby=style == "open_niche")


@category("tv_stand", "furniture", CABINET, ("living",), ("doors", "open_niche", "legs"))
def tv_stand(rng, style):
    """Low media cabinet, 1.2–2.0 m wide, top at 0.4–0.6 m."""
    width, depth, height = float(rng.uniform(1.2, 2.0)), float(rng.uniform(0.35, 0.5)), float(rng.uniform(0.4, 0.6))
    cols = int(rng.integers(2, 4))
    return _cabinet(rng, width, depth, height, 1, cols, legs=style == "legs", open_top_cubby=style == "open_niche")


@category("dresser", "furniture", CABINET, ("bedroom",), ("chest", "wide", "legs"))
def dresser(rng, style):
    """Chest of drawers, top at 0.75–1.05 m."""
    width = float(rng.uniform(1.1, 1.6) if style == "wide" else rng.uniform(0.8, 1.1))
    depth, height = float(rng.uniform(0.45, 0.55)), float(rng.uniform(0.75, 1.05))
    return _cabinet(rng, width, depth, height, int(rng.integers(3, 5)), 2 if style == "wide" else 1,
                    legs=style == "legs")


@category("wardrobe", "furniture", 90.0, ("bedroom",), ("two_doors", "three_doors"))
def wardrobe(rng, style):
    """Tall clothes cupboard, 1.8–2.2 m."""
    width = float(rng.uniform(0.9, 1.3) if style == "two_doors" else rng.uniform(1.3, 1.8))
    shape = _cabinet(rng, width, float(rng.uniform(0.55, 0.62)), float(rng.uniform(1.8, 2.2)), 1,
                     2 if style == "two_doors" else 3, legs=False)
    return shape
