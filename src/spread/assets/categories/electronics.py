"""Electronics: laptop, remote, phone, speaker, keyboard, monitor.

Build frame (metres, y-up, resting on y = 0, front +z: a laptop's hinge and a monitor's stand are at
−z, the user sits at +z). Bodies are solid, so densities are effective (a 1.5 kg laptop → ~900).
"""

from __future__ import annotations

import numpy as np

from spread.assets.categories.registry import category
from spread.assets.primitives import JOIN, box_between, frustum, hull, prism, rounded_slab
from spread.assets.shape import FLAT, Shape, rect_surface


@category("laptop", "object", 900.0, ("electronics", "office"), ("open", "closed"))
def laptop(rng, style):
    """Laptop, open (screen tilted back 100–120° about the rear hinge) or closed."""
    w, d = float(rng.uniform(0.3, 0.38)), float(rng.uniform(0.2, 0.26))
    base_t, lid_t = float(rng.uniform(0.012, 0.018)), float(rng.uniform(0.005, 0.008))
    parts = [rounded_slab((w, base_t, d), 0.01, (0.0, base_t / 2, 0.0))]
    if style == "closed":
        parts.append(rounded_slab((w, lid_t + JOIN, d), 0.01, (0.0, base_t + (lid_t - JOIN) / 2, 0.0)))
        return Shape(parts, [rect_surface(base_t + lid_t, -w / 2, -d / 2, w / 2, d / 2, 0.02)], FLAT)
    angle = np.radians(float(rng.uniform(100.0, 120.0)))
    hinge = np.array([base_t - 0.002, -d / 2 + 0.004])  # (y, z), a little inside the base
    corners = []
    for along in (0.0, d):  # from the hinge towards the screen's top edge
        for across in (0.0, lid_t):  # through the screen's thickness
            # closed screen: along → +z, across → +y; opening turns +z up and back by `angle`
            dz = along * np.cos(angle) - across * np.sin(angle)
            dy = along * np.sin(angle) + across * np.cos(angle)
            corners += [(x, hinge[0] + dy, hinge[1] + dz) for x in (-w / 2 + 0.005, w / 2 - 0.005)]
    parts.append(hull(corners))
    return Shape(parts, [rect_surface(base_t, -w / 2, -d / 2 + 0.02, w / 2, d / 2, 0.02)], FLAT)


@category("remote", "object", 550.0, ("electronics", "living"), ("buttons", "slim"))
def remote(rng, style):
    """TV remote: a rounded bar, with a raised button pad or slim."""
    w, t, length = float(rng.uniform(0.04, 0.06)), float(rng.uniform(0.015, 0.025)), float(rng.uniform(0.14, 0.22))
    parts = [rounded_slab((w, t, length), 0.01, (0.0, t / 2, 0.0))]
    if style == "buttons":
        parts.append(box_between((-w / 2 + 0.008, t - JOIN, -length / 4), (w / 2 - 0.008, t + 0.003, length / 3)))
    return Shape(parts, rest_poses=FLAT)


@category("phone", "object", 2000.0, ("electronics",), ("slim", "rugged"))
def phone(rng, style):
    """Smartphone lying screen up (a thin rounded slab; a rugged case is thicker and rounder)."""
    w, length = float(rng.uniform(0.065, 0.08)), float(rng.uniform(0.135, 0.165))
    t = float(rng.uniform(0.007, 0.009) if style == "slim" else rng.uniform(0.011, 0.015))
    body = rounded_slab((w, t, length), 0.008 if style == "slim" else 0.012, (0.0, t / 2, 0.0), 4)
    return Shape([body], rest_poses=FLAT)


@category("speaker", "object", 500.0, ("electronics", "living", "office"), ("box", "cylinder", "soundbar"))
def speaker(rng, style):
    """Speaker: a bookshelf box with a grille, a round smart speaker, or a low soundbar."""
    if style == "cylinder":
        r, h = float(rng.uniform(0.045, 0.075)), float(rng.uniform(0.1, 0.2))
        return Shape([prism(r, 0.0, h, 16), frustum(r, r * 0.8, h - JOIN, h + 0.012, 16)])
    if style == "soundbar":
        w, h, d = float(rng.uniform(0.5, 0.9)), float(rng.uniform(0.06, 0.09)), float(rng.uniform(0.08, 0.12))
    else:
        w, h, d = float(rng.uniform(0.12, 0.22)), float(rng.uniform(0.18, 0.33)), float(rng.uniform(0.15, 0.25))
    body = rounded_slab((w, h, d), 0.01, (0.0, h / 2, 0.0))
    grille = box_between((-w / 2 + 0.012, 0.01, d / 2 - JOIN), (w / 2 - 0.012, h - 0.01, d / 2 + 0.004))
    return Shape([body, grille])


@category("keyboard", "object", 400.0, ("electronics", "office"), ("full", "compact"))
def keyboard(rng, style):
    """Computer keyboard: a wedge rising towards the back with a block of keys on top."""
    w = float(rng.uniform(0.42, 0.46) if style == "full" else rng.uniform(0.28, 0.32))
    d, front, back = float(rng.uniform(0.12, 0.16)), float(rng.uniform(0.012, 0.016)), float(rng.uniform(0.022, 0.032))
    wedge_zy = ((d / 2, front), (-d / 2, back))  # (z, top height) at the front and back edges
    wedge = hull([(x, y, z) for x in (-w / 2, w / 2) for z, top in wedge_zy for y in (0.0, top)])
    keys_zy = ((d / 2 - 0.015, front), (-d / 2 + 0.01, back))
    keys = hull([(x, y, z) for x in (-w / 2 + 0.01, w / 2 - 0.01) for z, top in keys_zy
                 for y in (top - JOIN * 3, top + 0.008)])
    return Shape([wedge, keys], rest_poses=FLAT)


@category("monitor", "object", 500.0, ("electronics", "office"), ("stand", "round_foot"))
def monitor(rng, style):
    """Computer monitor: a thin screen on a neck over a flat foot (the neck at the back)."""
    w, h, t = float(rng.uniform(0.45, 0.7)), float(rng.uniform(0.28, 0.42)), float(rng.uniform(0.02, 0.04))
    lift = float(rng.uniform(0.08, 0.15))
    foot_d = float(rng.uniform(0.16, 0.22))
    if style == "round_foot":
        foot = prism(foot_d / 2, 0.0, 0.015, 16)
    else:
        foot = rounded_slab((float(rng.uniform(0.2, 0.28)), 0.015, foot_d), 0.02, (0.0, 0.0075, 0.0))
    z_neck = -foot_d / 2 + 0.04
    neck = box_between((-0.025, 0.015 - JOIN, z_neck - 0.015), (0.025, lift + h * 0.5, z_neck + 0.015))
    screen = box_between((-w / 2, lift, z_neck + 0.015 - JOIN), (w / 2, lift + h, z_neck + 0.015 + t))
    return Shape([foot, neck, screen])
