"""Images to files and contact sheets: atomic PNG writes, grids, before/after pairs (physics views)."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Sequence

import numpy as np

from spread.io import atomic_path
from spread.render.settings import TopDownRenderSettings
from spread.render.topdown import posed_meshes, render_topdown


def _as_rgb(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {image.shape} {image.dtype}")
    return image


def save_png(image: np.ndarray, path: str | os.PathLike) -> Path:
    """Write an (H, W, 3) uint8 image as PNG, atomically (a reader never sees a torn file)."""
    from PIL import Image

    path = Path(path)
    pil = Image.fromarray(_as_rgb(image), mode="RGB")
    with atomic_path(path, suffix=".png") as tmp:
        pil.save(tmp, format="PNG")
    return path


def render_grid(images: Sequence[np.ndarray], ncols: int, pad: int = 4,
                pad_colour: tuple[int, int, int] = (200, 200, 200)) -> np.ndarray:
    """Contact sheet: images row-major in ``ncols`` columns, cells of the largest image size, ``pad`` px gaps."""
    images = [_as_rgb(im) for im in images]
    if not images:
        raise ValueError("render_grid needs at least one image")
    if ncols < 1:
        raise ValueError(f"ncols must be ≥ 1, got {ncols}")
    ncols = min(ncols, len(images))
    nrows = -(-len(images) // ncols)
    ch = max(im.shape[0] for im in images)
    cw = max(im.shape[1] for im in images)
    sheet = np.empty((nrows * ch + (nrows + 1) * pad, ncols * cw + (ncols + 1) * pad, 3), np.uint8)
    sheet[:] = np.asarray(pad_colour, np.uint8)
    for k, im in enumerate(images):
        r, c = divmod(k, ncols)
        y, x = pad + r * (ch + pad), pad + c * (cw + pad)
        sheet[y:y + im.shape[0], x:x + im.shape[1]] = im
    return sheet


def render_before_after(scene_before, scene_after, library, settings: TopDownRenderSettings | None = None,
                        pad: int = 4) -> np.ndarray:
    """Before | after renders side by side, on one shared world window so displacements are comparable.

    Without explicit ``settings.bounds`` the window is the union of both scenes' rooms (or of their
    posed objects' xz bounds when a scene has no room).
    """
    settings = settings or TopDownRenderSettings()
    if settings.bounds is None:
        rects = [_xz_rect(s, library) for s in (scene_before, scene_after)]
        lo = np.minimum(rects[0][:2], rects[1][:2])
        hi = np.maximum(rects[0][2:], rects[1][2:])
        settings = replace(settings, bounds=(lo[0], lo[1], hi[0], hi[1]))
    return render_grid([render_topdown(scene_before, library, settings),
                        render_topdown(scene_after, library, settings)], ncols=2, pad=pad)


def _xz_rect(scene, library) -> np.ndarray:
    if scene.room is not None:
        room = np.asarray(scene.room, np.float64)
        return np.array([room[0, 0], room[0, 2], room[1, 0], room[1, 2]])
    v = np.concatenate([p.vertices for p in posed_meshes(scene, library)])
    return np.array([v[:, 0].min(), v[:, 2].min(), v[:, 0].max(), v[:, 2].max()])
