"""Top-down orthographic render of a scene: category-coloured silhouettes drawn bottom-up (DESIGN §6).

Each object's canonical mesh is posed (``v_world = R · v_local + t``), projected to the xz plane and
rasterised (:mod:`spread.render.raster`). Objects are painted in the order of their world top height
(max y of the posed mesh; ties keep scene order) *and* depth-tested per pixel: each pixel shows the
object whose surface is highest there (a z-buffer over the up-facing triangles), so a mug on a table
covers the table, and a book on a bed is not hidden by the bed's taller headboard. Orientation
and the world window are described in :mod:`spread.render.settings`: +x right, +z down the image.

Only the triangles that face up are rasterised when the mesh is a closed, consistently wound volume
(the silhouette of a closed surface is the union of its up-facing triangles); otherwise every
non-vertical triangle is. Vertical triangles project to segments and are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spread.render.palette import category_colours
from spread.render.raster import boundary_mask, paint_labels, point_pixels, triangle_pixels
from spread.render.settings import TopDownRenderSettings, make_window

#: |world normal y| below which a triangle counts as vertical (projects to a segment).
VERTICAL_NORMAL_Y = 1e-6


@dataclass
class PosedMesh:
    """One object's mesh in world coordinates (metres): vertices (V, 3), faces (F, 3), world normal y (F,)."""

    vertices: np.ndarray
    faces: np.ndarray
    normal_y: np.ndarray
    closed: bool


def _closed(mesh) -> bool:
    return bool(mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0)


def posed_meshes(scene, library) -> list[PosedMesh]:
    """Every object of ``scene`` posed in the world (the library's canonical meshes are not modified)."""
    out = []
    for aid, R, t in zip(scene.asset_id, scene.rotation.astype(np.float64), scene.translation.astype(np.float64)):
        mesh = library.mesh(str(aid))
        V = np.asarray(mesh.vertices, np.float64) @ R.T + t
        ny = np.asarray(mesh.face_normals, np.float64) @ R[1]  # world y of R · n_local
        out.append(PosedMesh(V, np.asarray(mesh.faces, np.int64), ny, _closed(mesh)))
    return out


def render_topdown(scene, library, settings: TopDownRenderSettings | None = None) -> np.ndarray:
    """(H, W, 3) uint8 top-down render of ``scene`` (white background, palette colours, bottom-up)."""
    settings = settings or TopDownRenderSettings()
    posed = posed_meshes(scene, library)
    obj_bounds = None
    if posed:
        allv = np.concatenate([p.vertices for p in posed])
        obj_bounds = (allv[:, 0].min(), allv[:, 2].min(), allv[:, 0].max(), allv[:, 2].max())
    window = make_window(settings, scene.room, obj_bounds)
    size = settings.image_size
    image = np.empty((size, size, 3), np.uint8)
    image[:] = np.asarray(settings.background, np.uint8)
    if settings.floor is not None and scene.room is not None:
        (c0, r0), (c1, r1) = window.to_pixels(np.asarray(scene.room, np.float64)[:, [0, 2]])
        rows = slice(max(int(round(r0)), 0), max(int(round(r1)), 0))
        cols = slice(max(int(round(c0)), 0), max(int(round(c1)), 0))
        image[rows, cols] = np.asarray(settings.floor, np.uint8)
    if not posed:
        return image

    tops = np.array([p.vertices[:, 1].max() for p in posed])
    order = np.argsort(tops, kind="stable")  # painter's order: lowest top first
    rank = np.empty(len(posed), np.int64)
    rank[order] = np.arange(len(posed))

    tris, tri_rank, tri_heights, verts, vert_rank, vert_heights = [], [], [], [], [], []
    for i, p in enumerate(posed):
        keep = p.normal_y > VERTICAL_NORMAL_Y if p.closed else np.abs(p.normal_y) > VERTICAL_NORMAL_Y
        xz = window.to_pixels(p.vertices[:, [0, 2]])
        tris.append(xz[p.faces[keep]])
        tri_heights.append(p.vertices[p.faces[keep], 1])
        tri_rank.append(np.full(int(keep.sum()), rank[i]))
        verts.append(xz)
        vert_heights.append(p.vertices[:, 1])
        vert_rank.append(np.full(len(xz), rank[i]))
    pix, tri, depth = triangle_pixels(np.concatenate(tris), size, size, np.concatenate(tri_heights))
    vpix, vidx = point_pixels(np.concatenate(verts), size, size)
    labels = paint_labels(np.concatenate([pix, vpix]),
                          np.concatenate([np.concatenate(tri_rank)[tri], np.concatenate(vert_rank)[vidx]]),
                          size, size,
                          depth=np.concatenate([depth, np.concatenate(vert_heights)[vidx]]))

    colours = category_colours(scene.category[order], settings.palette)  # row k = colour of rank k
    drawn = labels >= 0
    image[drawn] = colours[labels[drawn]]
    if settings.outline:
        edge = boundary_mask(labels)
        dark = np.floor(colours.astype(np.float64) * settings.outline_darken).astype(np.uint8)
        image[edge] = dark[labels[edge]]
    return image
