"""Headless images and exports: top-down category-coloured renders (FID protocol, DESIGN §6), perspective 3D
views, before | after physics, the relation matrix, scene cards; glb export.

Top-down images look straight down −y: +x to the right, +z down the image (see
:mod:`spread.render.settings`); 3D views look from the +z side by default, so +x is to the right there too
(:mod:`spread.render.camera`). Module table:

| module | does |
|---|---|
| :mod:`~spread.render.topdown`, :mod:`~spread.render.raster`, :mod:`~spread.render.settings` | top-down orthographic renders (numpy) |
| :mod:`~spread.render.camera` | pinhole camera, the default three-quarter view of a room |
| :mod:`~spread.render.perspective` | 3D views with pybullet's TinyRenderer (CPU, no display) |
| :mod:`~spread.render.relation_matrix` | which graph relations the poses realise (green / red cells) |
| :mod:`~spread.render.physics_view` | a scene after one Stability run |
| :mod:`~spread.render.figures` | labelled figures of the above (matplotlib, Agg) |
| :mod:`~spread.render.sheets`, :mod:`~spread.render.export` | PNG files, contact sheets; glb |
| :mod:`~spread.render.viewer` | ``spread-view``: scenes in an interactive 3D viewer in the browser (viser) |
"""
from spread.render.camera import Camera, fit_camera  # noqa: F401
from spread.render.export import build_trimesh_scene, export_glb  # noqa: F401
from spread.render.figures import (  # noqa: F401
    before_after_figure, legend_entries, relation_matrix_figure, scene_card_figure, scene_figure,
)
from spread.render.palette import PALETTES, category_colour, category_colours, hashed_colour  # noqa: F401
from spread.render.perspective import PerspectiveSettings, default_camera, render_perspective  # noqa: F401
from spread.render.physics_view import PhysicsOutcome, after_physics  # noqa: F401
from spread.render.relation_matrix import RelationAgreement, agreement_colours, relation_agreement  # noqa: F401
from spread.render.settings import VIEW_SETTINGS_FLOOR, TopDownRenderSettings  # noqa: F401
from spread.render.sheets import render_before_after, render_grid, save_png  # noqa: F401
from spread.render.topdown import render_topdown  # noqa: F401
