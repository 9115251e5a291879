"""Pieces that many furniture generators share: legs, aprons, cabinet carcasses, drawer fronts.

Build frame of :mod:`spread.assets.shape`: metres, y-up, floor y = 0, width along x, depth along z,
front towards +z.
"""

from __future__ import annotations

import numpy as np

from spread.assets.primitives import JOIN, box, box_between, post, rim


def corner_legs(width: float, depth: float, height: float, leg: float, inset: float,
                taper: float = 1.0, splay: float = 0.0) -> list:
    """Four legs from the floor up to ``height`` (+ :data:`JOIN` into what they carry).

    Leg centres sit ``inset + leg/2`` in from the ``width × depth`` rectangle's edges; ``taper`` scales
    the foot's side relative to the top's, ``splay`` moves each foot outwards by that many metres.
    """
    hx, hz = width / 2 - inset - leg / 2, depth / 2 - inset - leg / 2
    legs = []
    for sx in (-1, 1):
        for sz in (-1, 1):
            top = (sx * hx, sz * hz)
            foot = (sx * (hx + splay), sz * (hz + splay))
            legs.append(post(foot, top, 0.0, height + JOIN, leg * taper, leg))
    return legs


def apron(width: float, depth: float, y_top: float, height: float, thickness: float, inset: float) -> list:
    """The frame under a table top: a rectangular rim ``inset`` in from the top's edges."""
    return rim(width - 2 * inset, depth - 2 * inset, thickness, y_top - height, y_top + JOIN)


def board(width: float, depth: float, y0: float, thickness: float, centre_xz=(0.0, 0.0)):
    """Horizontal board (table top, shelf) from ``y0`` to ``y0 + thickness``."""
    return box((width, thickness, depth), (centre_xz[0], y0 + thickness / 2, centre_xz[1]))


def drawer_fronts(width: float, y0: float, y1: float, z_front: float, rows: int, cols: int,
                  gap: float = 0.004, proud: float = 0.012, knob: float = 0.02) -> list:
    """A grid of drawer/door fronts on a carcass face at ``z_front``, each with a knob.

    Fronts stand ``proud`` metres out and reach :data:`JOIN` into the carcass; knobs stick out 2 cm.
    """
    parts = []
    cell_w, cell_h = (width - gap) / cols, (y1 - y0 - gap) / rows
    for r in range(rows):
        for c in range(cols):
            x0, yb = -width / 2 + gap + c * cell_w, y0 + gap + r * cell_h
            x1, yt = x0 + cell_w - gap, yb + cell_h - gap
            parts.append(box_between((x0, yb, z_front - JOIN), (x1, yt, z_front + proud)))
            if knob > 0:
                kx, ky = (x0 + x1) / 2, (yb + yt) / 2
                parts.append(box((knob, knob, 0.02 + JOIN), (kx, ky, z_front + proud + 0.01 - JOIN / 2)))
    return parts


def plinth_or_legs(rng: np.random.Generator, width: float, depth: float, lift: float, legs: bool) -> list:
    """What a cabinet stands on: a recessed plinth box, or four short square legs of height ``lift``."""
    if legs:
        leg = float(rng.uniform(0.03, 0.05))
        return corner_legs(width, depth, lift, leg, inset=0.02, taper=0.7)
    return [box_between((-width / 2 + 0.03, 0.0, -depth / 2 + 0.02), (width / 2 - 0.03, lift + JOIN, depth / 2 - 0.05))]
