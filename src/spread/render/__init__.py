"""Headless renders and exports: top-down category-coloured images (FID protocol, DESIGN §6), glb.

Top-down images look straight down −y: +x to the right, +z down the image (see
:mod:`spread.render.settings`).
"""
from spread.render.export import build_trimesh_scene, export_glb  # noqa: F401
from spread.render.palette import PALETTES, category_colour, category_colours, hashed_colour  # noqa: F401
from spread.render.settings import VIEW_SETTINGS_FLOOR, TopDownRenderSettings  # noqa: F401
from spread.render.sheets import render_before_after, render_grid, save_png  # noqa: F401
from spread.render.topdown import render_topdown  # noqa: F401
