"""Kitchen and tableware: mug, cup, glass, wine_glass, bowl, plate, pan, pot, kettle, jar.

Build frame (metres, y-up, standing on y = 0, axis on y). Open vessels are modelled with true walls
(:mod:`spread.assets.categories.vessels`), so their effective density is the material's (ceramic
~2000, glass ~2500, aluminium ~2700). Bowls and plates offer their inner floor as a surface
("inside" / "top") for stacking and for fruit.
"""

from __future__ import annotations

import numpy as np

from spread.assets.categories.registry import category
from spread.assets.categories.vessels import add_side_handle, vessel
from spread.assets.primitives import JOIN, box_between, frustum, lathe, prism, strut
from spread.assets.shape import Shape, disc_surface

CERAMIC, GLASS, ALUMINIUM = 2000.0, 2500.0, 2700.0


@category("mug", "object", CERAMIC, ("kitchen", "tableware", "drinkware"), ("straight", "tapered", "wide"))
def mug(rng, style):
    """Mug with a handle, 8–12 cm tall."""
    height = float(rng.uniform(0.085, 0.115))
    r = float(rng.uniform(0.042, 0.05) if style == "wide" else rng.uniform(0.037, 0.045))
    taper = {"straight": 1.0, "tapered": float(rng.uniform(0.82, 0.9)), "wide": float(rng.uniform(0.92, 1.0))}[style]
    profile = [(0.0, r * taper), (height, r)]
    v = vessel(profile, float(rng.uniform(0.004, 0.006)), float(rng.uniform(0.006, 0.01)), 12)
    add_side_handle(v, profile, height * 0.2, height * 0.85, float(rng.uniform(0.022, 0.032)), 0.008,
                    float(rng.uniform(0.01, 0.014)))
    return Shape(v.parts)


@category("cup", "object", CERAMIC, ("kitchen", "tableware", "drinkware"), ("teacup", "espresso", "no_handle"))
def cup(rng, style):
    """Flared cup: a teacup or espresso cup with a small handle, or a handleless cup."""
    height = float(rng.uniform(0.045, 0.06) if style == "espresso" else rng.uniform(0.06, 0.085))
    r0 = float(rng.uniform(0.022, 0.03) if style == "espresso" else rng.uniform(0.026, 0.034))
    profile = [(0.0, r0), (height, r0 * float(rng.uniform(1.2, 1.45)))]
    v = vessel(profile, 0.004, 0.006, 12)
    if style != "no_handle":
        add_side_handle(v, profile, height * 0.3, height * 0.85, float(rng.uniform(0.015, 0.022)), 0.006, 0.009)
    return Shape(v.parts)


@category("glass", "object", GLASS, ("kitchen", "tableware", "drinkware"), ("tumbler", "highball", "flared"))
def glass(rng, style):
    """Drinking glass with a thick base: tumbler, highball or flared."""
    height = float(rng.uniform(0.08, 0.1) if style == "tumbler" else rng.uniform(0.12, 0.16))
    r = float(rng.uniform(0.033, 0.04) if style == "tumbler" else rng.uniform(0.028, 0.035))
    top = r * (float(rng.uniform(1.15, 1.3)) if style == "flared" else float(rng.uniform(1.0, 1.08)))
    v = vessel([(0.0, r), (height, top)], 0.003, float(rng.uniform(0.008, 0.015)), 12)
    return Shape(v.parts)


@category("wine_glass", "object", GLASS, ("kitchen", "tableware", "drinkware"), ("red", "white", "coupe"))
def wine_glass(rng, style):
    """Stemmed glass: foot, stem and a rounded bowl of two bands."""
    foot_r, stem_h = float(rng.uniform(0.032, 0.04)), float(rng.uniform(0.06, 0.09))
    bowl_h = float(rng.uniform(0.04, 0.05) if style == "coupe" else rng.uniform(0.08, 0.11))
    r_max = float(rng.uniform(0.045, 0.055) if style == "red" else rng.uniform(0.035, 0.045))
    r_rim = r_max * (1.05 if style == "coupe" else float(rng.uniform(0.75, 0.88)))
    profile = [(0.0, 0.012), (bowl_h * 0.45, r_max), (bowl_h, r_rim)]
    y_bowl = 0.004 + stem_h
    v = vessel(profile, 0.0025, 0.006, 10, y0=y_bowl)
    v.parts += [frustum(foot_r, foot_r * 0.35, 0.0, 0.004, 12), prism(0.0045, 0.004 - JOIN, y_bowl + 0.003, 8)]
    return Shape(v.parts)


@category("bowl", "object", CERAMIC, ("kitchen", "tableware", "stackable", "container"), ("rounded", "deep", "shallow"))
def bowl(rng, style):
    """Bowl of 13–23 cm diameter, rounded by two wall bands; its inner floor holds fruit or another bowl."""
    r_top = float(rng.uniform(0.065, 0.115))
    height = r_top * {"rounded": float(rng.uniform(0.5, 0.65)), "deep": float(rng.uniform(0.65, 0.8)),
                      "shallow": float(rng.uniform(0.3, 0.4))}[style]
    profile = [(0.0, r_top * 0.6), (height * 0.5, r_top * 0.9), (height, r_top)]
    v = vessel(profile, float(rng.uniform(0.004, 0.006)), float(rng.uniform(0.005, 0.008)), 10)
    surface = disc_surface(v.floor_height, v.floor_radius, 0.003, kind="inside")
    return Shape(v.parts, [surface])


@category("plate", "object", CERAMIC, ("kitchen", "tableware", "stackable"), ("dinner", "side", "deep"))
def plate(rng, style):
    """Plate: flat floor and a low flared rim, 16–28 cm across."""
    r = float(rng.uniform(0.12, 0.14) if style == "dinner" else rng.uniform(0.08, 0.11))
    height = float(rng.uniform(0.03, 0.045) if style == "deep" else rng.uniform(0.015, 0.025))
    floor_r = r * float(rng.uniform(0.6, 0.72))
    v = vessel([(0.0, floor_r), (height, r)], 0.005, 0.005, 16)
    return Shape(v.parts, [disc_surface(v.floor_height, v.floor_radius, 0.004)])


@category("pan", "object", ALUMINIUM, ("kitchen", "cookware"), ("frying", "saute", "small"))
def pan(rng, style):
    """Frying pan with a long handle rising from the rim."""
    r_top = float(rng.uniform(0.07, 0.09) if style == "small" else rng.uniform(0.1, 0.14))
    height = float(rng.uniform(0.06, 0.075) if style == "saute" else rng.uniform(0.035, 0.05))
    flare = 1.0 if style == "saute" else float(rng.uniform(0.8, 0.9))
    profile = [(0.0, r_top * flare), (height, r_top)]
    v = vessel(profile, 0.004, 0.005, 16)
    x0 = v.apothem_at(profile, height * 0.7) - 0.002
    length = float(rng.uniform(0.14, 0.2))
    v.parts.append(strut((x0, height * 0.7, 0.0), (x0 + length, height * 0.7 + length * 0.25, 0.0), 0.012, 0.022))
    return Shape(v.parts)


@category("pot", "object", ALUMINIUM, ("kitchen", "cookware"), ("stock", "saucepan", "dutch"))
def pot(rng, style):
    """Cooking pot: stock pot or Dutch oven with two side grips, or a saucepan with a long handle."""
    r = float(rng.uniform(0.07, 0.1) if style == "saucepan" else rng.uniform(0.1, 0.13))
    height = r * float(rng.uniform(1.0, 1.4) if style == "stock" else rng.uniform(0.6, 0.9))
    profile = [(0.0, r), (height, r)]
    v = vessel(profile, 0.004, 0.006, 14)
    a = v.apothem_at(profile, height)
    if style == "saucepan":
        length = float(rng.uniform(0.14, 0.2))
        y = height * 0.8
        v.parts.append(strut((a - 0.002, y, 0.0), (a + length, y + length * 0.2, 0.0), 0.012, 0.022))
    else:
        y = height - 0.025
        for sx in (-1, 1):
            lo, hi = (a - 0.002, a + 0.03) if sx > 0 else (-a - 0.03, -a + 0.002)
            v.parts.append(box_between((lo, y, -0.03), (hi, y + 0.012, 0.03)))
    return Shape(v.parts)


@category("kettle", "object", 500.0, ("kitchen",), ("dome", "cylinder"))
def kettle(rng, style):
    """Closed kettle (solid body, effective density), spout on −x, handle over the top or on +x."""
    r, height = float(rng.uniform(0.07, 0.09)), float(rng.uniform(0.16, 0.22))
    if style == "dome":
        profile = [(0.0, r), (height * 0.55, r * 1.05), (height * 0.9, r * 0.6), (height, r * 0.3)]
    else:
        profile = [(0.0, r), (height * 0.9, r * 0.92), (height, r * 0.5)]
    parts = lathe(profile, 14)
    parts.append(strut((-r * 0.7, height * 0.35, 0.0), (-r - 0.05, height * 0.75, 0.0), 0.02, 0.02))
    if style == "dome":
        top = height * 0.95
        for z in (-0.035, 0.035):
            parts.append(box_between((-0.01, top - 0.06, z - 0.008), (0.01, top + 0.05, z + 0.008)))
        parts.append(box_between((-0.012, top + 0.04, -0.035 - 0.008), (0.012, top + 0.055, 0.035 + 0.008)))
    else:
        x = r * 0.9 * np.cos(np.pi / 14)
        parts += [box_between((x - 0.01, height * 0.78, -0.01), (x + 0.05, height * 0.86, 0.01)),
                  box_between((x - 0.01, height * 0.2, -0.01), (x + 0.05, height * 0.28, 0.01)),
                  box_between((x + 0.03, height * 0.28 - JOIN, -0.01), (x + 0.05, height * 0.78 + JOIN, 0.01))]
    return Shape(parts)


@category("jar", "object", 800.0, ("kitchen", "pantry"), ("tall", "squat"))
def jar(rng, style):
    """Closed storage jar with a lid (solid: its contents count in the effective density)."""
    r = float(rng.uniform(0.03, 0.045) if style == "tall" else rng.uniform(0.045, 0.06))
    height = r * float(rng.uniform(2.5, 3.5) if style == "tall" else rng.uniform(1.2, 1.8))
    neck = r * float(rng.uniform(0.75, 0.9))
    body = lathe([(0.0, r), (height * 0.82, r), (height * 0.9, neck)], 14)
    lid = prism(neck + 0.004, height * 0.9 - JOIN, height, 14)
    return Shape(body + [lid])
