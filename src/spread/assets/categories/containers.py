"""Containers and packaging: bottle, can, tray, basket, cutting_board, box, tissue_box.

Build frame (metres, y-up, standing on y = 0). Bottles and cans are polygonal prisms (10–12 sides,
a flat face towards +x) so that lying on the side they rest on a face instead of rolling; the lying
pose is validated like any other. Trays and baskets offer their inner floor ("inside"; open above,
except under a basket's carrying arch).
"""

from __future__ import annotations

import numpy as np

from spread.assets.categories.registry import category
from spread.assets.categories.vessels import vessel
from spread.assets.primitives import JOIN, box, box_between, ellipsoid, frustum, prism, rim, rounded_slab
from spread.assets.shape import FLAT, LIE_ON_SIDE, Shape, disc_surface, rect_surface

LYING = {"upright": 0.8, "lying": 0.2}


@category("bottle", "object", 900.0, ("kitchen", "drinkware"), ("wine", "water", "square"))
def bottle(rng, style):
    """Closed bottle (solid, filled): body, shoulder, neck and cap sharing one polygon orientation."""
    sides = 4 if style == "square" else 10
    r = float(rng.uniform(0.035, 0.045) if style == "water" else rng.uniform(0.03, 0.04))
    body_h = float(rng.uniform(0.15, 0.22) if style == "wine" else rng.uniform(0.12, 0.18))
    shoulder_h = float(rng.uniform(0.03, 0.05))
    neck_r = float(rng.uniform(0.012, 0.016))
    neck_h = float(rng.uniform(0.07, 0.1) if style == "wine" else rng.uniform(0.02, 0.04))
    y1, y2 = body_h + shoulder_h, body_h + shoulder_h + neck_h
    parts = [
        prism(r, 0.0, body_h, sides),
        frustum(r, neck_r, body_h - JOIN, y1, sides),
        prism(neck_r, y1 - JOIN, y2, sides),
        prism(neck_r + 0.002, y2 - 0.015, y2 + 0.01, sides),
    ]
    return Shape(parts, rest_poses={"upright": np.eye(3), "lying": LIE_ON_SIDE}, rest_weights=LYING)


@category("can", "object", 900.0, ("kitchen", "drinkware", "pantry"), ("soda", "tall", "food"))
def can(rng, style):
    """Drink or food can: a 12-sided prism with narrower rims at both ends."""
    r = float(rng.uniform(0.037, 0.043) if style == "food" else rng.uniform(0.027, 0.034))
    height = float({"soda": rng.uniform(0.11, 0.125), "tall": rng.uniform(0.15, 0.17),
                    "food": rng.uniform(0.075, 0.115)}[style])
    parts = [
        frustum(r * 0.9, r, 0.0, 0.008, 12),
        prism(r, 0.008 - JOIN, height - 0.01 + JOIN, 12),
        frustum(r, r * 0.9, height - 0.01, height, 12),
    ]
    return Shape(parts, rest_poses={"upright": np.eye(3), "lying": LIE_ON_SIDE}, rest_weights=LYING)


@category("tray", "object", 700.0, ("kitchen", "living", "stackable", "container"), ("rect", "handles", "round"))
def tray(rng, style):
    """Serving tray: a floor with a low rim (rectangular, with end grips, or round)."""
    height, floor_t, wall = float(rng.uniform(0.02, 0.045)), 0.008, float(rng.uniform(0.006, 0.01))
    if style == "round":
        r = float(rng.uniform(0.15, 0.2))
        v = vessel([(0.0, r), (height, r * 1.03)], wall, floor_t, 16)
        return Shape(v.parts, [disc_surface(v.floor_height, v.floor_radius, 0.01, kind="inside")])
    width, depth = float(rng.uniform(0.35, 0.5)), float(rng.uniform(0.25, 0.35))
    parts = [box_between((-width / 2 + JOIN, 0.0, -depth / 2 + JOIN), (width / 2 - JOIN, floor_t, depth / 2 - JOIN))]
    parts += rim(width, depth, wall, 0.0, height)
    if style == "handles":
        for sx in (-1, 1):
            x0, x1 = sorted((sx * (width / 2 - wall / 2), sx * (width / 2 + 0.03)))
            parts.append(box_between((x0, height - 0.012, -0.05), (x1, height, 0.05)))
    surface = rect_surface(floor_t, -width / 2 + wall, -depth / 2 + wall, width / 2 - wall, depth / 2 - wall, 0.01,
                           kind="inside")
    return Shape(parts, [surface])


@category("basket", "object", 500.0, ("living", "kitchen", "container"), ("open", "handled", "round"))
def basket(rng, style):
    """Woven basket (true walls): rectangular, rectangular with a carrying arch, or round and flared."""
    height, floor_t, wall = float(rng.uniform(0.1, 0.22)), 0.01, float(rng.uniform(0.008, 0.012))
    if style == "round":
        r = float(rng.uniform(0.1, 0.16))
        v = vessel([(0.0, r), (height, r * float(rng.uniform(1.1, 1.25)))], wall, floor_t, 12)
        return Shape(v.parts, [disc_surface(v.floor_height, v.floor_radius, 0.01, kind="inside")])
    width, depth = float(rng.uniform(0.25, 0.4)), float(rng.uniform(0.18, 0.3))
    parts = [box_between((-width / 2 + JOIN, 0.0, -depth / 2 + JOIN), (width / 2 - JOIN, floor_t, depth / 2 - JOIN))]
    parts += rim(width, depth, wall, 0.0, height)
    top = height
    if style == "handled":
        top = height + float(rng.uniform(0.08, 0.12))
        for sx in (-1, 1):
            x0 = sx * (width / 2 - wall / 2)
            parts.append(box_between((x0 - 0.008, height - 0.02, -0.012), (x0 + 0.008, top, 0.012)))
        x = width / 2 - wall / 2 + 0.008
        parts.append(box_between((-x, top - 0.016, -0.012), (x, top, 0.012)))
    surface = rect_surface(floor_t, -width / 2 + wall, -depth / 2 + wall, width / 2 - wall, depth / 2 - wall, 0.01,
                           clearance=top - 0.016 - floor_t if style == "handled" else float("inf"), kind="inside")
    return Shape(parts, [surface])


@category("cutting_board", "object", 700.0, ("kitchen", "stackable"), ("plain", "handle"))
def cutting_board(rng, style):
    """Wooden cutting board with rounded corners, optionally with a handle tab on +x."""
    length, width, t = float(rng.uniform(0.3, 0.45)), float(rng.uniform(0.2, 0.3)), float(rng.uniform(0.015, 0.03))
    parts = [rounded_slab((length, t, width), 0.02, (0.0, t / 2, 0.0))]
    if style == "handle":
        parts.append(rounded_slab((0.1, t, 0.06), 0.02, (length / 2 + 0.03, t / 2, 0.0)))
    return Shape(parts, [rect_surface(t, -length / 2, -width / 2, length / 2, width / 2, 0.02)], FLAT)


@category("box", "object", 150.0, ("storage", "office", "stackable"), ("plain", "lidded", "shoebox"))
def box_(rng, style):
    """Closed cardboard box (effective density with contents), optionally with an overhanging lid."""
    if style == "shoebox":
        w, h, d = float(rng.uniform(0.3, 0.36)), float(rng.uniform(0.1, 0.13)), float(rng.uniform(0.18, 0.22))
    else:
        w, h, d = (float(v) for v in rng.uniform([0.12, 0.06, 0.1], [0.45, 0.3, 0.35]))
    parts = [box((w, h, d), (0.0, h / 2, 0.0))]
    top = h
    if style != "plain":
        lid_h = min(0.04, h * 0.3)
        top = h + 0.002
        parts.append(box_between((-w / 2 - 0.003, top - lid_h, -d / 2 - 0.003), (w / 2 + 0.003, top, d / 2 + 0.003)))
    return Shape(parts, [rect_surface(top, -w / 2, -d / 2, w / 2, d / 2, 0.01)], FLAT)


@category("tissue_box", "object", 100.0, ("bedroom", "living", "bathroom"), ("flat", "cube"))
def tissue_box(rng, style):
    """Tissue box with a puff of tissue sticking out of the top."""
    if style == "cube":
        w = float(rng.uniform(0.11, 0.13))
        size = (w, w * float(rng.uniform(1.0, 1.15)), w)
    else:
        size = (float(rng.uniform(0.22, 0.26)), float(rng.uniform(0.07, 0.1)), float(rng.uniform(0.11, 0.13)))
    parts = [box(size, (0.0, size[1] / 2, 0.0))]
    parts.append(ellipsoid((0.04, 0.025, 0.03), (0.0, size[1] + 0.005, 0.0), rings=3, sides=8))
    return Shape(parts)
