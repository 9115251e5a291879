"""spread-export format=sceneeval: SceneEval's scene-state JSON (z-up, column-major transforms) whose
transforms put each exported mesh exactly where the platform's scene puts it."""

from __future__ import annotations

import json

import numpy as np
import trimesh

from spread.export import export_scene
from spread.export.sceneeval import Y_UP_TO_Z_UP
from spread.scene import MOUNT_CEILING, MOUNT_FLOOR, MOUNT_ON_OBJECT, write_scene
from helpers import scene_of
from test_mujoco import build_box_library


def room(library):
    scene = scene_of(["table", "cup", "cube"], [[0.0, 0.375, 0.0], [0.2, 0.8, 0.1], [1.5, 2.5, -0.4]],
                     [np.eye(3), np.eye(3), trimesh.transformations.rotation_matrix(0.6, [0, 1, 0])[:3, :3]],
                     library=library, posed_codes=True, scene_id="se|room")
    scene.physical[0, 1] = 1
    scene.extras["mount"] = np.array([MOUNT_FLOOR, MOUNT_ON_OBJECT, MOUNT_CEILING], np.int8)
    scene.room = np.array([[-2.0, 0.0, -1.5], [2.5, 2.7, 1.5]], np.float32)
    return scene


def test_sceneeval_state_places_every_mesh_where_the_scene_does(tmp_path):
    library = build_box_library(tmp_path / "lib")
    scene = room(library)
    folder = export_scene(scene, library, tmp_path / "out", "sceneeval")
    state = json.loads((folder / "scene_state.json").read_text())
    assert state["format"] == "sceneState" and state["scene"]["version"] == "scene@1.0.2"
    assert state["scene"]["up"] == [0, 0, 1] and state["scene"]["unit"] == 1.0
    objs = state["scene"]["object"]
    assert [o["index"] for o in objs] == [0, 1, 2] and [o["parentIndex"] for o in objs] == [-1, 0, -1]
    assert [o["spreadMount"] for o in objs] == ["floor", "on_object", "ceiling"]
    for i, o in enumerate(objs):
        T = np.array(o["transform"]["data"]).reshape(4, 4).T  # column-major
        mesh = trimesh.load(folder / o["mesh"], force="mesh", process=False)
        exported = mesh.vertices @ T[:3, :3].T + T[:3, 3]
        ours = library.mesh(str(scene.asset_id[i])).vertices @ scene.rotation[i].T.astype(np.float64) \
            + scene.translation[i]
        assert np.abs(exported @ Y_UP_TO_Z_UP - ours).max() < 1e-5  # back to y-up: the same points
        assert o["modelId"] == f"spread.{scene.asset_id[i]}"
    arch = state["scene"]["arch"]
    floor = [e for e in arch["elements"] if e["type"] == "Floor"][0]
    xy = np.array(floor["points"])[:, :2]
    assert np.allclose(sorted(xy[:, 0]), [-2, -2, 2.5, 2.5]) and np.allclose(sorted(xy[:, 1]), [-1.5, -1.5, 1.5, 1.5])
    assert np.allclose([e["height"] for e in arch["elements"] if e["type"] == "Wall"], [2.7] * 4)


def test_the_export_command_writes_sceneeval_folders(tmp_path):
    from helpers import compose

    from spread.commands.export import export

    library = build_box_library(tmp_path / "assets")
    scenes = tmp_path / "scenes"
    write_scene(room(library), scenes / "a.npz")
    report = export(compose("export", f"scenes={scenes}", f"assets={tmp_path / 'assets'}", "format=sceneeval",
                            f"out_dir={tmp_path / 'se'}", "progress=false"))
    assert not report.failed and len(report.written) == 1
    assert len(list((tmp_path / "se").glob("*/scene_state.json"))) == 1
