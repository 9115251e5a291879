"""Decor and lighting: vase, plant_pot, lamp, floor_lamp, candle, clock, picture_frame, pillow.

Build frame (metres, y-up, standing on y = 0, front +z). Lamps and plant pots are solid (effective
densities); vases are hollow with true ceramic walls.
"""

from __future__ import annotations

import numpy as np

from spread.assets.categories.registry import category
from spread.assets.categories.vessels import vessel
from spread.assets.primitives import (
    JOIN, box_between, ellipsoid, frustum, horizontal_prism, hull, prism, rounded_slab,
)
from spread.assets.shape import FLAT, Shape


@category("vase", "object", 2000.0, ("decor",), ("cylinder", "bulb", "flared"))
def vase(rng, style):
    """Hollow ceramic vase, 15–40 cm: a cylinder, a bulb with a neck, or a flared cone."""
    height, r = float(rng.uniform(0.15, 0.4)), float(rng.uniform(0.04, 0.08))
    if style == "cylinder":
        profile = [(0.0, r), (height, r * float(rng.uniform(0.95, 1.05)))]
    elif style == "bulb":
        profile = [(0.0, r * 0.8), (height * 0.4, r * 1.35), (height, r * float(rng.uniform(0.55, 0.75)))]
    else:
        profile = [(0.0, r * 0.7), (height * 0.5, r * 0.8), (height, r * float(rng.uniform(1.4, 1.8)))]
    return Shape(vessel(profile, 0.005, 0.01, 10).parts)


@category("plant_pot", "object", 350.0, ("decor", "living"), ("bush", "succulents", "tall"))
def plant_pot(rng, style):
    """Flower pot filled with soil and a plant (foliage as convex blobs)."""
    r0, height = float(rng.uniform(0.05, 0.09)), float(rng.uniform(0.08, 0.16))
    r1 = r0 * float(rng.uniform(1.15, 1.35))
    parts = [frustum(r0, r1, 0.0, height, 14), prism(r1 + 0.006, height - 0.02, height, 14)]
    if style == "bush":
        size = r1 * float(rng.uniform(0.9, 1.25))
        parts.append(ellipsoid((size, size * float(rng.uniform(0.8, 1.2)), size), (0.0, height + size * 0.7, 0.0)))
    elif style == "succulents":
        for k in range(int(rng.integers(2, 5))):
            a, d = rng.uniform(0, 2 * np.pi), r1 * float(rng.uniform(0.0, 0.45))
            s = r1 * float(rng.uniform(0.3, 0.5))
            parts.append(ellipsoid((s, s * 0.7, s), (d * np.cos(a), height + s * 0.4, d * np.sin(a)), rings=4, sides=8))
    else:
        stem_h = float(rng.uniform(0.1, 0.25))
        parts.append(prism(0.012, height - 0.01, height + stem_h, 8))
        crown = r1 * float(rng.uniform(1.0, 1.4))
        centre = (0.0, height + stem_h + crown * 0.9, 0.0)
        parts.append(ellipsoid((crown, crown * 1.4, crown), centre, rings=6, sides=10))
    return Shape(parts)


def _lamp_head(stem_top: float, shade_r: float, shade_h: float) -> list:
    """Solid lampshade (frustum, wider at the bottom) whose lower rim sits at ``stem_top``."""
    return [frustum(shade_r, shade_r * 0.7, stem_top - 0.02, stem_top - 0.02 + shade_h, 16)]


@category("lamp", "object", 300.0, ("decor", "lighting", "bedroom", "living"), ("stem", "ball_base", "column"))
def lamp(rng, style):
    """Table lamp: base, stem and shade, 30–60 cm tall."""
    base_r = float(rng.uniform(0.06, 0.1))
    stem_top = float(rng.uniform(0.2, 0.38))
    shade_r, shade_h = float(rng.uniform(0.1, 0.18)), float(rng.uniform(0.14, 0.22))
    if style == "ball_base":
        parts = [ellipsoid((base_r, base_r, base_r), (0.0, base_r * 0.9, 0.0), cut_below=0.0),
                 prism(0.01, base_r, stem_top, 8)]
    elif style == "column":
        parts = [prism(base_r * 0.6, 0.0, stem_top, 12)]
    else:
        parts = [frustum(base_r, base_r * 0.8, 0.0, 0.025, 14), prism(0.01, 0.025 - JOIN, stem_top, 8)]
    return Shape(parts + _lamp_head(stem_top, shade_r, shade_h))


@category("floor_lamp", "furniture", 150.0, ("lighting", "living", "bedroom"), ("shade", "cone"))
def floor_lamp(rng, style):
    """Standing lamp: heavy round foot, pole, shade; 1.4–1.8 m tall."""
    base_r = float(rng.uniform(0.14, 0.2))
    stem_top = float(rng.uniform(1.2, 1.5))
    parts = [frustum(base_r, base_r * 0.85, 0.0, 0.03, 16), prism(0.014, 0.03 - JOIN, stem_top, 8)]
    if style == "shade":
        parts += _lamp_head(stem_top, float(rng.uniform(0.18, 0.25)), float(rng.uniform(0.25, 0.35)))
    else:
        parts.append(frustum(0.05, float(rng.uniform(0.15, 0.22)), stem_top - 0.02, stem_top + 0.2, 16))
    return Shape(parts)


@category("candle", "object", 900.0, ("decor", "dining"), ("pillar", "jar", "taper"))
def candle(rng, style):
    """Pillar candle, candle in a glass jar, or a taper candle in a holder."""
    if style == "taper":
        foot_r = float(rng.uniform(0.035, 0.05))
        length = float(rng.uniform(0.15, 0.25))
        parts = [frustum(foot_r, foot_r * 0.4, 0.0, 0.02, 12), prism(0.014, 0.02 - JOIN, 0.06, 10),
                 prism(0.01, 0.05, 0.05 + length, 10)]
        top = 0.05 + length
    else:
        r = float(rng.uniform(0.025, 0.045) if style == "pillar" else rng.uniform(0.035, 0.05))
        top = float(rng.uniform(0.06, 0.15) if style == "pillar" else rng.uniform(0.07, 0.1))
        parts = [prism(r, 0.0, top, 14)]
        if style == "jar":
            parts.append(prism(r + 0.003, top - 0.01, top + 0.012, 14))
            top += 0.012
    parts.append(prism(0.0015, top - JOIN, top + 0.01, 6))
    return Shape(parts)


@category("clock", "object", 400.0, ("decor", "bedroom", "office"), ("round", "stand", "box"))
def clock(rng, style):
    """Table clock: a 12-sided disc standing on a face, a round disc on a base, or a box clock."""
    if style == "box":
        w, h, d = float(rng.uniform(0.08, 0.14)), float(rng.uniform(0.06, 0.1)), float(rng.uniform(0.04, 0.07))
        return Shape([rounded_slab((w, h, d), 0.012, (0.0, h / 2, 0.0))])
    r, t = float(rng.uniform(0.05, 0.1)), float(rng.uniform(0.03, 0.05))
    if style == "round":
        # 12 sides: it stands on a flat face; with 16 or more it would roll (see spread.assets.stability)
        return Shape([horizontal_prism(r, t, (0.0, r * np.cos(np.pi / 12), 0.0), axis="z", sides=12)])
    base_h = float(rng.uniform(0.015, 0.025))
    y = base_h + r * 0.85
    return Shape([box_between((-r * 0.8, 0.0, -t * 0.9), (r * 0.8, base_h, t * 0.9)),
                  horizontal_prism(r, t, (0.0, y, 0.0), axis="z", sides=16)])


@category("picture_frame", "object", 600.0, ("decor", "bedroom", "living", "office"), ("portrait", "landscape"))
def picture_frame(rng, style):
    """Standing photo frame leaning back 10–15° on a kickstand behind it.

    The frame is a sheared slab whose bottom face lies flat on the floor (front edge at z = 0), so it
    stands on that face and on the kickstand's foot.
    """
    a, b = float(rng.uniform(0.1, 0.2)), float(rng.uniform(0.13, 0.28))
    width, height = (a, b) if style == "portrait" else (b, a)
    t, tilt = float(rng.uniform(0.01, 0.02)), np.radians(float(rng.uniform(10.0, 15.0)))
    depth = t / np.cos(tilt)  # horizontal thickness of the leaning slab

    def back_z(y: float) -> float:
        """z of the slab's back face at height y."""
        return -y * np.tan(tilt) - depth

    top = height * np.cos(tilt)
    slab = hull([(x, y, z) for x in (-width / 2, width / 2) for y in (0.0, top)
                 for z in (-y * np.tan(tilt), back_z(y))])
    y_mid = 0.55 * top
    foot_z = back_z(0.0) - 0.35 * height
    stand_yz = ((y_mid + 0.01, back_z(y_mid + 0.01) + 0.004), (y_mid, back_z(y_mid) + 0.004),
                (0.0, foot_z), (0.0, foot_z + 0.012))
    stand = hull([(x, y, z) for x in (-0.008, 0.008) for y, z in stand_yz])
    return Shape([slab, stand])


@category("pillow", "object", 60.0, ("bedroom", "living", "soft"), ("square", "rectangular", "bolster"))
def pillow(rng, style):
    """Cushion or pillow lying flat (a rounded, flattened superellipsoid), or a bolster on a face."""
    if style == "bolster":
        r, length = float(rng.uniform(0.08, 0.11)), float(rng.uniform(0.4, 0.6))
        bolster = horizontal_prism(r, length, (0.0, r * np.cos(np.pi / 12), 0.0), axis="x", sides=12)
        return Shape([bolster], rest_poses=FLAT)
    w = float(rng.uniform(0.38, 0.5))
    d = w if style == "square" else float(rng.uniform(0.3, 0.4))
    if style == "rectangular":
        w = float(rng.uniform(0.5, 0.7))
    h = float(rng.uniform(0.1, 0.16))
    return Shape([ellipsoid((w / 2, h / 2, d / 2), (0.0, h / 2, 0.0), rings=5, sides=16, squareness=2.5,
                            cut_below=-h * 0.35)], rest_poses=FLAT)
