"""A scene in SceneEval's scene-state format (github.com/3dlg-hcvc/SceneEval: ``scene_state_template.json``,
``scenes/scene_state.py``), so generated rooms can be cross-checked with that harness.

Folder ``<id>/`` with ``scene_state.json`` and ``meshes/<asset>.obj`` (each asset's canonical mesh: metres,
its own y-up frame centred at the bbox centre, the frame the platform poses). The JSON::

    {"format": "sceneState", "selected": [],
     "scene": {"version": "scene@1.0.2", "id", "up": [0, 0, 1], "front": [0, 1, 0], "unit": 1.0,
               "assetSource": ["spread"], "arch": {...}, "object": [...]}}

Frames: SceneEval's world is **z-up**; the platform's is y-up. World points map by ``M = R_x(+90°)``,
``(x, y, z) → (x, −z, y)``. Object ``i`` (``modelId`` = ``spread.<asset id>``, mesh ``meshes/<safe id>.obj``)
has ``transform.data`` = the column-major 4 × 4 of ``[[M·R_i, M·t_i], [0, 0, 0, 1]]`` (model frame → SceneEval
world; a model's up, +y, becomes +z as for SceneEval's 3D-FUTURE models), with ``rotation`` (its quaternion,
x y z w), ``translation`` and ``scale`` (1). ``parentIndex`` is the object's supporter (``physical``), −1 on
the floor. ``arch``: a floor polygon (the room's rectangle, as the other exports' floor) and four walls of the
room's height (2.8 m without a room). Extra keys ``spreadCategory`` and ``spreadMount`` name each object's
category and mount.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

#: y-up (platform) → z-up (SceneEval) world rotation: (x, y, z) → (x, −z, y).
Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
DEFAULT_HEIGHT = 2.8


def _arch(scene) -> dict:
    from spread.export.urdf import floor_rect

    x0, z0, x1, z1 = floor_rect(scene, margin=0.0)
    height = float(scene.room[1, 1]) if scene.room is not None and scene.room[1, 1] > 0.5 else DEFAULT_HEIGHT
    corners = [(x0, z0), (x1, z0), (x1, z1), (x0, z1)]
    pts = [[float(x), float(-z), 0.0] for x, z in corners]  # y-up (x, 0, z) → z-up (x, −z, 0)
    area = sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(pts, pts[1:] + pts[:1]))
    if area < 0:  # counter-clockwise seen from +z
        pts = pts[::-1]
    elements = [{"id": 0, "roomId": "0", "type": "Floor", "depth": 0.05, "points": pts}]
    for k in range(4):
        elements.append({"id": k + 1, "roomId": "0", "type": "Wall", "height": height, "depth": 0.1, "holes": [],
                         "points": [pts[k], pts[(k + 1) % 4]]})
    return {"version": "arch@1.0.2", "id": f"{scene.scene_id}-arch", "up": [0, 0, 1], "front": [0, 1, 0],
            "coords2d": [0, 1], "scaleToMeters": 1, "elements": elements,
            "regions": [{"id": "0", "type": "Other", "walls": [1, 2, 3, 4]}], "holes": [], "materials": [],
            "textures": [], "images": []}


def sceneeval_state(scene) -> dict:
    """The scene-state dict of ``scene`` (module docstring)."""
    from spread.io import safe_name
    from spread.physics.frames import matrix_to_quat
    from spread.scene import MOUNT_NAMES, scene_mounts

    mounts = scene_mounts(scene)
    supporters = np.full(scene.num_objects, -1)
    for i, j in scene.support_pairs():
        supporters[j] = i
    objects = []
    for i, aid in enumerate(str(a) for a in scene.asset_id):
        R = Y_UP_TO_Z_UP @ np.asarray(scene.rotation[i], np.float64)
        t = Y_UP_TO_Z_UP @ np.asarray(scene.translation[i], np.float64)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t
        objects.append({
            "id": str(i + 1), "index": i, "modelId": f"spread.{aid}", "mesh": f"meshes/{safe_name(aid)}.obj",
            "parentId": "" if supporters[i] < 0 else str(int(supporters[i]) + 1), "parentIndex": int(supporters[i]),
            "transform": {"rows": 4, "cols": 4, "data": T.T.reshape(-1).tolist(),
                          "rotation": matrix_to_quat(R[None])[0].tolist(), "translation": t.tolist(),
                          "scale": [1.0, 1.0, 1.0]},
            "spreadCategory": str(scene.category[i]), "spreadMount": MOUNT_NAMES[int(mounts[i])]})
    return {"format": "sceneState", "selected": [],
            "scene": {"version": "scene@1.0.2", "id": str(scene.scene_id), "up": [0, 0, 1], "front": [0, 1, 0],
                      "unit": 1.0, "assetSource": ["spread"], "arch": _arch(scene), "object": objects}}


def write_sceneeval_scene(scene, library, folder: Path) -> Path:
    """Write ``folder/scene_state.json`` and the meshes it names (``folder`` exists and is empty)."""
    from spread.export.urdf import write_obj
    from spread.io import safe_name

    (folder / "meshes").mkdir()
    for aid in dict.fromkeys(str(a) for a in scene.asset_id):
        mesh = library.mesh(aid)
        write_obj(folder / "meshes" / f"{safe_name(aid)}.obj", mesh.vertices, mesh.faces)
    path = folder / "scene_state.json"
    path.write_text(json.dumps(sceneeval_state(scene), indent=1) + "\n")
    return path
