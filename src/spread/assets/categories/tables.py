"""Tables and counters: dining_table, coffee_table, side_table, desk, kitchen_counter.

Build frame (metres, y-up, floor y = 0, front +z). Every table top is a "top" support surface at the
top face's height, inset 4 cm from the edges; lower shelves are "shelf" surfaces with the clearance up
to the underside of the top.
"""

from __future__ import annotations

import numpy as np

from spread.assets.categories.furniture_parts import apron, board, corner_legs, drawer_fronts
from spread.assets.categories.registry import category
from spread.assets.primitives import JOIN, box_between, frustum, prism
from spread.assets.shape import Shape, disc_surface, rect_surface

WOOD = 600.0
INSET = 0.04


def _rect_table(rng, width, depth, height, with_apron=True, lower_shelf=False, taper=1.0) -> Shape:
    """Rectangular top on four legs, optionally with an apron and a lower shelf."""
    top_t = float(rng.uniform(0.025, 0.045))
    leg = float(rng.uniform(0.04, 0.07))
    leg_inset = float(rng.uniform(0.02, 0.07))
    y_under = height - top_t
    parts = [board(width, depth, y_under, top_t)] + corner_legs(width, depth, y_under, leg, leg_inset, taper)
    if with_apron:
        parts += apron(width, depth, y_under, float(rng.uniform(0.06, 0.1)), 0.02, leg_inset + leg / 2 - 0.01)
    surfaces = [rect_surface(height, -width / 2, -depth / 2, width / 2, depth / 2, INSET)]
    if lower_shelf:
        y_shelf, t = float(rng.uniform(0.08, 0.15)), 0.018
        span_w, span_d = width - 2 * leg_inset - 2 * leg + 2 * JOIN, depth - 2 * leg_inset
        parts.append(board(span_w, span_d, y_shelf, t))
        surfaces.append(rect_surface(y_shelf + t, -span_w / 2, -span_d / 2, span_w / 2, span_d / 2, 0.02,
                                     clearance=y_under - (y_shelf + t), kind="shelf"))
    return Shape(parts, surfaces)


def _round_pedestal_table(rng, radius, height, sides=20) -> Shape:
    """Round top on a central column and a wide foot (a flat disc or a low cone)."""
    top_t = float(rng.uniform(0.025, 0.04))
    foot_r = radius * float(rng.uniform(0.5, 0.65))
    foot_h = float(rng.uniform(0.03, 0.06))
    column_r = float(rng.uniform(0.035, 0.06))
    parts = [
        prism(radius, height - top_t, height, sides),
        frustum(foot_r, foot_r * 0.6, 0.0, foot_h, 16),
        prism(column_r, foot_h - JOIN, height - top_t + JOIN, 12),
    ]
    return Shape(parts, [disc_surface(height, radius * np.cos(np.pi / sides), INSET)])


@category("dining_table", "furniture", WOOD, ("dining", "kitchen"), ("four_legs", "round_pedestal", "trestle"))
def dining_table(rng, style):
    """Dining table, top at 0.72–0.78 m."""
    height = float(rng.uniform(0.72, 0.78))
    if style == "round_pedestal":
        return _round_pedestal_table(rng, float(rng.uniform(0.45, 0.6)), height)
    width, depth = float(rng.uniform(1.2, 2.0)), float(rng.uniform(0.8, 1.0))
    if style == "four_legs":
        return _rect_table(rng, width, depth, height, taper=float(rng.uniform(0.7, 1.0)))
    top_t = float(rng.uniform(0.03, 0.045))
    y_under = height - top_t
    x_leg = width / 2 - float(rng.uniform(0.15, 0.25))
    panel_t, foot_d = float(rng.uniform(0.05, 0.08)), depth * 0.8
    parts = [board(width, depth, y_under, top_t)]
    for sx in (-1, 1):
        x = sx * x_leg
        parts += [
            box_between((x - 0.04, 0.0, -foot_d / 2), (x + 0.04, 0.05, foot_d / 2)),
            box_between((x - panel_t / 2, 0.05 - JOIN, -0.05), (x + panel_t / 2, y_under + JOIN, 0.05)),
        ]
    parts.append(box_between((-x_leg, 0.2, -0.025), (x_leg, 0.26, 0.025)))  # stretcher
    return Shape(parts, [rect_surface(height, -width / 2, -depth / 2, width / 2, depth / 2, INSET)])


@category("coffee_table", "furniture", WOOD, ("living",), ("four_legs", "lower_shelf", "slab_sides"))
def coffee_table(rng, style):
    """Low living-room table, top at 0.38–0.48 m."""
    height = float(rng.uniform(0.38, 0.48))
    width, depth = float(rng.uniform(0.9, 1.3)), float(rng.uniform(0.5, 0.7))
    if style != "slab_sides":
        return _rect_table(rng, width, depth, height, with_apron=style == "four_legs",
                           lower_shelf=style == "lower_shelf")
    top_t, side_t = float(rng.uniform(0.03, 0.05)), float(rng.uniform(0.03, 0.05))
    parts = [board(width, depth, height - top_t, top_t)]
    x_out = width / 2 - 0.01
    for x0, x1 in ((-x_out, -x_out + side_t), (x_out - side_t, x_out)):
        parts.append(box_between((x0, 0.0, -depth / 2 + 0.01), (x1, height - top_t + JOIN, depth / 2 - 0.01)))
    return Shape(parts, [rect_surface(height, -width / 2, -depth / 2, width / 2, depth / 2, INSET)])


@category("side_table", "furniture", WOOD, ("living", "bedroom"), ("four_legs", "round_pedestal", "lower_shelf"))
def side_table(rng, style):
    """Small end table, top at 0.5–0.65 m."""
    height = float(rng.uniform(0.5, 0.65))
    if style == "round_pedestal":
        return _round_pedestal_table(rng, float(rng.uniform(0.22, 0.3)), height, sides=16)
    size = float(rng.uniform(0.4, 0.55))
    return _rect_table(rng, size, size * float(rng.uniform(0.85, 1.0)), height, with_apron=style == "four_legs",
                       lower_shelf=style == "lower_shelf", taper=float(rng.uniform(0.7, 1.0)))


@category("desk", "furniture", 400.0, ("office", "bedroom"), ("four_legs", "drawer_pedestal", "panel_legs"))
def desk(rng, style):
    """Writing desk, top at 0.72–0.76 m, 1.1–1.6 m wide."""
    height = float(rng.uniform(0.72, 0.76))
    width, depth = float(rng.uniform(1.1, 1.6)), float(rng.uniform(0.55, 0.75))
    if style == "four_legs":
        return _rect_table(rng, width, depth, height)
    top_t = float(rng.uniform(0.025, 0.035))
    y_under = height - top_t
    parts = [board(width, depth, y_under, top_t)]
    panel_t = float(rng.uniform(0.02, 0.035))
    if style == "drawer_pedestal":
        ped_w = float(rng.uniform(0.35, 0.45))
        x0 = width / 2 - ped_w
        parts.append(box_between((x0, 0.0, -depth / 2 + 0.02), (width / 2 - 0.01, y_under + JOIN, depth / 2 - 0.03)))
        fronts = drawer_fronts(ped_w - 0.01, 0.02, y_under - 0.01, depth / 2 - 0.03, 3, 1)
        parts += [f.apply_translation((x0 + (ped_w - 0.01) / 2, 0, 0)) for f in fronts]
        parts.append(box_between((-width / 2 + 0.01, 0.0, -depth / 2 + 0.02),
                                 (-width / 2 + 0.01 + panel_t, y_under + JOIN, depth / 2 - 0.03)))
    else:
        for sx in (-1, 1):
            x_out = sx * (width / 2 - 0.01)
            parts.append(box_between((min(x_out, x_out - sx * panel_t), 0.0, -depth / 2 + 0.02),
                                     (max(x_out, x_out - sx * panel_t), y_under + JOIN, depth / 2 - 0.02)))
        parts.append(box_between((-width / 2 + 0.01 + panel_t - JOIN, y_under - 0.35, -depth / 2 + 0.04),
                                 (width / 2 - 0.01 - panel_t + JOIN, y_under + JOIN, -depth / 2 + 0.06)))
    return Shape(parts, [rect_surface(height, -width / 2, -depth / 2, width / 2, depth / 2, INSET)])


@category("kitchen_counter", "furniture", 180.0, ("kitchen",), ("doors", "drawers", "mixed"))
def kitchen_counter(rng, style):
    """Base cabinet run with an overhanging worktop, worktop at 0.88–0.94 m."""
    height = float(rng.uniform(0.88, 0.94))
    width, depth = float(rng.uniform(0.6, 2.0)), float(rng.uniform(0.6, 0.65))
    top_t = float(rng.uniform(0.03, 0.04))
    plinth = float(rng.uniform(0.08, 0.12))
    body_d = depth - 0.03
    z_front = -depth / 2 + body_d
    parts = [
        board(width, depth, height - top_t, top_t),
        box_between((-width / 2 + 0.005, plinth - JOIN, -depth / 2 + 0.005),
                    (width / 2 - 0.005, height - top_t + JOIN, z_front)),
        box_between((-width / 2 + 0.03, 0.0, -depth / 2 + 0.02), (width / 2 - 0.03, plinth, z_front - 0.06)),
    ]
    cols = min(3, max(1, int(round(width / 0.5))))  # fronts (and knobs) are parts: keep them few
    y0, y1 = plinth, height - top_t
    if style == "doors":
        parts += drawer_fronts(width, y0, y1, z_front, 1, cols)
    elif style == "drawers":
        parts += drawer_fronts(width, y0, y1, z_front, 3, cols)
    else:
        y_split = y1 - 0.16
        parts += drawer_fronts(width, y_split, y1, z_front, 1, cols, knob=0.0)
        parts += drawer_fronts(width, y0, y_split, z_front, 1, cols)
    return Shape(parts, [rect_surface(height, -width / 2, -depth / 2, width / 2, depth / 2, 0.03)])
