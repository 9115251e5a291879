"""Scene export to glTF binary (``.glb``) for viewers and simulators.

Each object is a node named ``<index>_<asset_id>`` holding its own copy of the canonical mesh
(metres, bbox-centred) with the node transform ``[R | t]`` (world-from-local), so the file keeps both
the asset geometry and the pose; the material's base colour is the category's palette colour. An
optional floor is a thin box (:data:`FLOOR_THICKNESS`) whose top face is the plane y = 0, spanning the
room's xz rectangle (or the objects' xz bounds grown by :data:`FLOOR_MARGIN` when the scene has no room).
glTF is y-up in metres, like our frame, so no axis change is needed.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from spread.io import atomic_path
from spread.render.palette import DEFAULT_PALETTE, category_colour

FLOOR_THICKNESS = 0.02  # metres
FLOOR_MARGIN = 0.5  # metres around the objects when there is no room rectangle
FLOOR_COLOUR = (190, 190, 190, 255)


def _material(name: str, rgba):
    from trimesh.visual.material import PBRMaterial

    return PBRMaterial(name=name, baseColorFactor=list(rgba), metallicFactor=0.0, roughnessFactor=0.9)


def build_trimesh_scene(scene, library, floor: bool = True, palette: str = DEFAULT_PALETTE):
    """A ``trimesh.Scene`` of the posed objects (+ floor): the in-memory form of :func:`export_glb`."""
    import trimesh

    out = trimesh.Scene()
    for i, (aid, cat) in enumerate(zip(scene.asset_id, scene.category)):
        canon = library.mesh(str(aid))
        mesh = trimesh.Trimesh(np.array(canon.vertices), np.array(canon.faces), process=False)
        name = f"{i}_{aid}"
        mesh.visual = trimesh.visual.TextureVisuals(material=_material(name, (*category_colour(str(cat), palette), 255)))
        T = np.eye(4)
        T[:3, :3] = scene.rotation[i]
        T[:3, 3] = scene.translation[i]
        out.add_geometry(mesh, node_name=name, geom_name=name, transform=T)
    if floor:
        if scene.room is not None:
            room = np.asarray(scene.room, np.float64)
            x0, z0, x1, z1 = room[0, 0], room[0, 2], room[1, 0], room[1, 2]
        else:
            lo, hi = out.bounds if len(out.geometry) else (np.zeros(3), np.zeros(3))  # world bounds of the posed objects
            x0, z0 = lo[0] - FLOOR_MARGIN, lo[2] - FLOOR_MARGIN
            x1, z1 = hi[0] + FLOOR_MARGIN, hi[2] + FLOOR_MARGIN
        box = trimesh.creation.box(extents=[x1 - x0, FLOOR_THICKNESS, z1 - z0])
        box.apply_translation([(x0 + x1) / 2, -FLOOR_THICKNESS / 2, (z0 + z1) / 2])
        box.visual = trimesh.visual.TextureVisuals(material=_material("floor", FLOOR_COLOUR))
        out.add_geometry(box, node_name="floor", geom_name="floor")
    return out


def export_glb(scene, library, path: str | os.PathLike, floor: bool = True, palette: str = DEFAULT_PALETTE) -> Path:
    """Write ``scene`` as a binary glTF at ``path`` atomically; returns the path."""
    path = Path(path)
    data = build_trimesh_scene(scene, library, floor=floor, palette=palette).export(file_type="glb")
    with atomic_path(path, suffix=".glb") as tmp:
        tmp.write_bytes(data)
    return path
