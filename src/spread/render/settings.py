"""Settings of the top-down renderer, and the world window they map onto the image.

Camera: orthographic, looking straight down −y (from above). Image columns grow with world **+x**
(+x points right) and image rows grow with world **+z** (+z points DOWN the image). This is a proper
(unmirrored) view from above of a right-handed y-up frame: right = +x, out of the screen = +y, so
down = +x × +y = +z.

World window: the xz rectangle ``bounds`` = (x_min, z_min, x_max, z_max) in metres if given, else the
scene's ``room`` floor rectangle, else the xz bounds of the posed objects; grown by ``margin`` metres on
every side, then grown symmetrically along its shorter side to a square, so one pixel covers the same
length in x and z (no distortion). Pixel (row r, column c) covers
``x ∈ [x0 + c·s, x0 + (c+1)·s)``, ``z ∈ [z0 + r·s, z0 + (r+1)·s)`` with ``s`` metres per pixel.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Sequence

import numpy as np

from spread.render.palette import DEFAULT_PALETTE, PALETTES


@dataclass(frozen=True)
class TopDownRenderSettings:
    """Everything that changes a top-down render; record it with :meth:`to_dict` beside the images."""

    image_size: int = 256  # square image, pixels
    background: tuple[int, int, int] = (255, 255, 255)  # uint8 RGB, white by default
    margin: float = 0.25  # metres added around the bounds on every side
    bounds: tuple[float, float, float, float] | None = None  # (x_min, z_min, x_max, z_max) metres
    palette: str = DEFAULT_PALETTE
    outline: bool = True  # 1-pixel darker outline on each visible object's boundary
    outline_darken: float = 0.55  # outline colour = fill colour × this
    floor: tuple[int, int, int] | None = None  # fill the scene's room floor with this RGB (None: background)

    def __post_init__(self) -> None:
        if int(self.image_size) < 8:
            raise ValueError(f"image_size must be at least 8 pixels, got {self.image_size}")
        if len(self.background) != 3 or not all(0 <= int(v) <= 255 for v in self.background):
            raise ValueError(f"background must be an RGB triple of 0..255, got {self.background}")
        if not np.isfinite(self.margin) or self.margin < 0:
            raise ValueError(f"margin must be a finite number of metres ≥ 0, got {self.margin}")
        if self.palette not in PALETTES:
            raise ValueError(f"unknown palette '{self.palette}' (known: {sorted(PALETTES)})")
        if not 0.0 <= self.outline_darken <= 1.0:
            raise ValueError(f"outline_darken must be in [0, 1], got {self.outline_darken}")
        if self.bounds is not None:
            b = np.asarray(self.bounds, float)
            if b.shape != (4,) or not np.isfinite(b).all() or b[2] < b[0] or b[3] < b[1]:
                raise ValueError(f"bounds must be finite (x_min, z_min, x_max, z_max) with max ≥ min, got {self.bounds}")
            object.__setattr__(self, "bounds", tuple(float(v) for v in b))
        object.__setattr__(self, "background", tuple(int(v) for v in self.background))
        if self.floor is not None:
            if len(self.floor) != 3 or not all(0 <= int(v) <= 255 for v in self.floor):
                raise ValueError(f"floor must be None or an RGB triple of 0..255, got {self.floor}")
            object.__setattr__(self, "floor", tuple(int(v) for v in self.floor))
        object.__setattr__(self, "image_size", int(self.image_size))

    def to_dict(self) -> dict:
        d = asdict(self)
        d["background"] = list(self.background)
        d["floor"] = None if self.floor is None else list(self.floor)
        d["bounds"] = None if self.bounds is None else list(self.bounds)
        d["orientation"] = "orthographic from +y looking down -y; +x right, +z down the image"
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "TopDownRenderSettings":
        d = {k: v for k, v in d.items() if k != "orientation"}
        if d.get("bounds") is not None:
            d["bounds"] = tuple(d["bounds"])
        if "background" in d:
            d["background"] = tuple(d["background"])
        if d.get("floor") is not None:
            d["floor"] = tuple(d["floor"])
        return cls(**d)


#: Settings for people to look at (README, demo, notebooks): the room's floor in light grey.
#: FID renders use the plain defaults (white background, no floor) per DESIGN §6.
VIEW_SETTINGS_FLOOR = (232, 228, 220)


@dataclass(frozen=True)
class Window:
    """The square world xz window of an image: origin (x0, z0) in metres and metres per pixel."""

    x0: float
    z0: float
    metres_per_pixel: float
    size: int

    def to_pixels(self, xz: np.ndarray) -> np.ndarray:
        """(..., 2) world (x, z) metres → continuous (column, row) pixel coordinates."""
        xz = np.asarray(xz, np.float64)
        return (xz - np.array([self.x0, self.z0])) / self.metres_per_pixel


def make_window(settings: TopDownRenderSettings, room: np.ndarray | None,
                object_xz_bounds: Sequence[float] | None) -> Window:
    """The window for ``settings``: explicit bounds, else room (2, 3) min/max, else object bounds."""
    if settings.bounds is not None:
        x_min, z_min, x_max, z_max = settings.bounds
    elif room is not None:
        room = np.asarray(room, np.float64)
        x_min, z_min, x_max, z_max = room[0, 0], room[0, 2], room[1, 0], room[1, 2]
    elif object_xz_bounds is not None:
        x_min, z_min, x_max, z_max = object_xz_bounds
    else:
        raise ValueError("no bounds: give settings.bounds, a scene room or objects")
    x_min, z_min = x_min - settings.margin, z_min - settings.margin
    x_max, z_max = x_max + settings.margin, z_max + settings.margin
    side = max(x_max - x_min, z_max - z_min, 1e-3)
    cx, cz = 0.5 * (x_min + x_max), 0.5 * (z_min + z_max)
    return Window(x0=float(cx - side / 2), z0=float(cz - side / 2),
                  metres_per_pixel=float(side / settings.image_size), size=settings.image_size)
