"""Fixed per-category colours for renders and exports (DESIGN §6: "a fixed per-category palette").

Palette ``spread-v1`` is a literal table, so colours never drift with code changes: 43 household
categories, picked once by greedy farthest-point selection in CIELAB over a 16-level sRGB grid with
lightness limited to 30 < L* < 85 (so no colour is near white or near black). The smallest CIELAB
distance between two table colours is 27.7 and to white 34.6. Unknown categories get a stable
hash-based colour (sha256 of the name → hue, saturation ≥ 0.5, value ≤ 0.85: never white), identical
across processes and machines (Python's ``hash`` is salted per process, so it is not used).
"""

from __future__ import annotations

import colorsys
import hashlib
from typing import Iterable

import numpy as np

DEFAULT_PALETTE = "spread-v1"

_SPREAD_V1 = {
    "dining_table": "#0000ff", "coffee_table": "#00ee00", "side_table": "#ff0000", "desk": "#881166",
    "kitchen_counter": "#ffcc00", "shelf": "#115511", "bookcase": "#0099ff", "nightstand": "#773300",
    "tv_stand": "#00eebb", "dresser": "#ff00ee", "bed": "#445566", "sofa": "#ffaaff", "armchair": "#4433bb",
    "chair": "#ff6677", "stool": "#bbcc77", "mug": "#00ccee", "cup": "#ffaa66", "bowl": "#00aa33",
    "plate": "#aadd11", "bottle": "#ff0099", "vase": "#bb8888", "book": "#008877", "laptop": "#887700",
    "remote": "#ff7700", "phone": "#aabbee", "box": "#8866aa", "pan": "#cc66ee", "pot": "#aa0000",
    "fruit": "#aa33ff", "lamp": "#665533", "candle": "#990033", "pillow": "#99ddbb", "tray": "#1188bb",
    "basket": "#55aa66", "can": "#004499", "toy": "#889988", "pencil": "#ff0044", "glass": "#7777ee",
    "jar": "#cc6699", "clock": "#880099", "plant_pot": "#773344", "speaker": "#0044ff", "keyboard": "#558800",
}

#: name → {category: (r, g, b)}; the palette a settings object names must be a key here.
PALETTES: dict[str, dict[str, tuple[int, int, int]]] = {
    DEFAULT_PALETTE: {k: tuple(int(v[i:i + 2], 16) for i in (1, 3, 5)) for k, v in _SPREAD_V1.items()},
}


def hashed_colour(name: str) -> tuple[int, int, int]:
    """A stable, saturated, never-white colour for a category name outside the table."""
    h = hashlib.sha256(name.encode("utf-8")).digest()
    hue = h[0] / 256.0 + h[1] / 65536.0
    sat = 0.5 + 0.4 * h[2] / 255.0
    val = 0.45 + 0.4 * h[3] / 255.0
    r, g, b = colorsys.hsv_to_rgb(hue, sat, val)
    return int(round(r * 255)), int(round(g * 255)), int(round(b * 255))


def category_colour(category: str, palette: str = DEFAULT_PALETTE) -> tuple[int, int, int]:
    """(r, g, b) uint8 colour of a category: the table entry, else :func:`hashed_colour`."""
    try:
        table = PALETTES[palette]
    except KeyError:
        raise ValueError(f"unknown palette '{palette}' (known: {sorted(PALETTES)})") from None
    return table.get(category) or hashed_colour(category)


def category_colours(categories: Iterable[str], palette: str = DEFAULT_PALETTE) -> np.ndarray:
    """(N, 3) uint8 colours for a sequence of category names."""
    cols = [category_colour(str(c), palette) for c in categories]
    return np.asarray(cols, dtype=np.uint8).reshape(-1, 3)
