"""spread-export: URDF loads in pybullet, MJCF in MuJoCo, USD in pxr, and a settled room stays put in each;
scene ids cannot write outside ``out_dir``; bad scenes are reported, the others exported.

The room is ``test_mujoco``'s settled box room (a table with a box and a cylinder cup on it, a box in a
U-shaped trough, an L and a two-box tower on the floor), in metres, y-up.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from spread.export import FORMATS, export_folder, export_path, export_scene
from spread.io import safe_name
from spread.metrics import STILL_ANGLE, STILL_DISTANCE
from spread.physics import displacement_stats
from spread.relations import scene_spatial_codes
from spread.scene import write_scene

from helpers import scene_of
from test_mujoco import build_box_library, settled_box_room

STEPS, DT, SUBSTEPS = 100, 1.0 / 60.0, 4  # 100 steps of 1/60 s, each as 4 internal steps


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A dataset-like folder: ``assets/`` (the box library) and ``test/`` holding the settled room."""
    root = tmp_path_factory.mktemp("export_data")
    library = build_box_library(root / "assets")
    scene = settled_box_room(library, scene_id="room|1")
    write_scene(scene, root / "test" / "room_1.npz")
    return root, library, scene


def assert_stays_put(scene, library, translation, rotation):
    """The Stability rule: every object still (< 1 cm, < 0.1 rad) and every spatial code unchanged."""
    moved = displacement_stats((scene.translation, scene.rotation), (translation, rotation))
    assert moved.distance.max() < STILL_DISTANCE and moved.angle.max() < STILL_ANGLE
    ids = [str(a) for a in scene.asset_id]
    assert np.array_equal(scene_spatial_codes(translation.astype(np.float32), rotation.astype(np.float32), ids,
                                              library), scene.spatial)


# ---- safe names ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("hostile", ["../x", "/etc/passwd", "a/b/../../c", "..", ".", "", ".hidden", "nul",
                                     "room|4", "x" * 400, "é\x00\n"])
def test_safe_name_is_one_harmless_path_component(hostile):
    name = safe_name(hostile)
    assert name and "/" not in name and "\\" not in name and "\x00" not in name
    assert name not in (".", "..") and not name.startswith(".") and len(name) <= 120
    assert Path(name).name == name
    assert safe_name(hostile) == name  # deterministic


def test_safe_name_keeps_safe_ids_and_separates_ids_that_clean_alike():
    assert safe_name("s0_000001") == "s0_000001"
    assert len({safe_name(t) for t in ("a/b", "a_b", "a|b", "a:b")}) == 4


# ---- per format -------------------------------------------------------------------------------------------

def test_urdf_room_loads_in_pybullet_and_stays_put(data, tmp_path):
    import pybullet as pb

    from spread.export.urdf import load_urdf_scene, urdf_scene_poses

    _, library, scene = data
    folder = export_scene(scene, library, tmp_path, "urdf")
    assert folder == tmp_path.resolve() / safe_name(scene.scene_id) and (folder / "scene.json").exists()
    client = pb.connect(pb.DIRECT)
    try:
        bodies = load_urdf_scene(folder / "scene.json", client)
        assert len(bodies["objects"]) == scene.num_objects and bodies["floor"] is not None
        masses = [pb.getDynamicsInfo(b, -1, physicsClientId=client)[0] for b in bodies["objects"]]
        assert np.allclose(masses, [library[a].mass for a in scene.asset_id], rtol=1e-9)
        t0, R0 = urdf_scene_poses(bodies["objects"], client)
        assert np.abs(t0 - scene.translation).max() < 1e-6 and np.abs(R0 - scene.rotation).max() < 1e-6
        pb.setPhysicsEngineParameter(fixedTimeStep=DT, numSubSteps=SUBSTEPS, physicsClientId=client)
        for _ in range(STEPS):
            pb.stepSimulation(physicsClientId=client)
        assert_stays_put(scene, library, *urdf_scene_poses(bodies["objects"], client))
    finally:
        pb.disconnect(client)


def mjcf_poses(model, data) -> tuple[np.ndarray, np.ndarray]:
    """Scene poses (y-up) of the bodies of an exported MJCF (z-up: x → x, y → z, z → −y)."""
    zy = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # z-up world → y-up world
    return data.xpos[1:] @ zy.T, np.einsum("ij,njk->nik", zy, data.xmat[1:].reshape(-1, 3, 3))


def test_mjcf_room_loads_in_mujoco_and_stays_put(data, tmp_path):
    import mujoco

    _, library, scene = data
    path = export_scene(scene, library, tmp_path, "mjcf")
    model = mujoco.MjModel.from_xml_path(str(path))
    assert model.nbody == scene.num_objects + 1
    assert np.allclose(model.body_mass[1:], [library[a].mass for a in scene.asset_id], rtol=1e-9)
    assert (model.geom_group == 1).sum() == scene.num_objects  # one visual mesh per object
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    t0, R0 = mjcf_poses(model, d)
    assert np.abs(t0 - scene.translation).max() < 1e-6 and np.abs(R0 - scene.rotation).max() < 1e-6
    mujoco.mj_step(model, d, nstep=round(STEPS * DT / model.opt.timestep))
    assert_stays_put(scene, library, *mjcf_poses(model, d))


def test_usd_room_has_one_rigid_body_per_object_and_one_collider_per_part(data, tmp_path):
    from pxr import Usd, UsdGeom, UsdPhysics

    from spread.physics.mjcf import asset_geometry

    _, library, scene = data
    path = export_scene(scene, library, tmp_path, "usd")
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    prims = list(stage.Traverse())
    bodies = [p for p in prims if p.HasAPI(UsdPhysics.RigidBodyAPI)]
    colliders = [p for p in prims if p.HasAPI(UsdPhysics.CollisionAPI)]
    parts = sum(asset_geometry(library, str(a)).num_geoms for a in scene.asset_id)
    assert len(bodies) == scene.num_objects and len(colliders) == parts + 1  # + the floor
    for i, body in enumerate(bodies):
        assert UsdPhysics.MassAPI(body).GetMassAttr().Get() == pytest.approx(library[scene.asset_id[i]].mass)
        T = np.array(UsdGeom.Xformable(body).ComputeLocalToWorldTransform(Usd.TimeCode.Default()))
        assert np.allclose(T[3, :3], scene.translation[i], atol=1e-6)  # USD: row vectors, translation last row
        assert np.allclose(T[:3, :3].T, scene.rotation[i], atol=1e-6)
    load = getattr(UsdPhysics, "UsdPhysicsLoadStageFromPrimRange", None) or UsdPhysics.LoadUsdPhysicsFromRange
    parsed = {str(k): len(v[0]) for k, v in load(stage, ["/World"]).items()}  # the UsdPhysics reference parser
    assert parsed["RigidBody"] == scene.num_objects and parsed["Scene"] == 1
    assert parsed.get("CubeShape", 0) + parsed.get("MeshShape", 0) == parts + 1


def test_glb_holds_every_object_and_the_floor(data, tmp_path):
    import trimesh

    _, library, scene = data
    loaded = trimesh.load(export_scene(scene, library, tmp_path, "glb"), force="scene")
    assert len(loaded.geometry) == scene.num_objects + 1


# ---- layout, atomic writes, bad input ---------------------------------------------------------------------

@pytest.mark.parametrize("fmt", FORMATS)
def test_hostile_scene_ids_write_nothing_outside_out_dir(data, tmp_path, fmt):
    _, library, scene = data
    out = tmp_path / "deep" / "out"
    for k, hostile in enumerate(["../escaped", "/tmp/abs_escape", "a/../../b", "..", "x/y"]):
        small = scene_of(["box"], [[0.0, 0.1, 0.0]], library=library, posed_codes=True, scene_id=hostile)
        written = export_scene(small, library, out, fmt)
        assert written.parent == out.resolve()
    outside = [p for p in tmp_path.rglob("*") if out.resolve() not in (p.resolve(), *p.resolve().parents)
               and p.resolve() not in out.resolve().parents]
    assert outside == []
    assert len(os.listdir(out)) == 5 and not [n for n in os.listdir(out) if n.startswith(".")]  # no temporaries


def test_reexport_replaces_a_urdf_folder_whole(data, tmp_path):
    _, library, scene = data
    folder = export_scene(scene, library, tmp_path, "urdf")
    (folder / "stale.txt").write_text("from an older export")
    export_scene(scene, library, tmp_path, "urdf")
    assert not (folder / "stale.txt").exists() and (folder / "scene.json").exists()
    assert sorted(os.listdir(tmp_path)) == [folder.name]


def test_bad_scene_is_reported_and_the_others_exported(data, tmp_path):
    root, library, scene = data
    scenes = tmp_path / "scenes"
    write_scene(scene, scenes / "good.npz")
    bad = scene_of(["box"], [[0.0, 0.1, 0.0]], library=library, posed_codes=True, scene_id="bad")
    bad.asset_id = np.array(["no_such_asset"])
    write_scene(bad, scenes / "bad.npz", validate=False)
    report = export_folder(scenes, root / "assets", tmp_path / "out", "mjcf")
    assert list(report.written) == ["room|1"] and list(report.failed) == ["bad"]
    assert "no_such_asset" in report.failed["bad"] and "bad.npz" in report.failed["bad"]
    saved = json.loads((tmp_path / "out" / "export.json").read_text())
    assert saved["n_written"] == 1 and saved["n_failed"] == 1
    with pytest.raises(ValueError, match="unknown export format"):
        export_path(tmp_path, "x", "sdf")


def write_copies(scene, folder: Path, names=("a", "b", "c")) -> None:
    """``folder/<name>.npz``: ``scene`` under each scene id of ``names``."""
    import copy

    for name in names:
        one = copy.deepcopy(scene)
        one.scene_id = name
        write_scene(one, folder / f"{name}.npz")


def test_a_reexport_removes_the_outputs_it_no_longer_writes_and_nothing_else(data, tmp_path):
    root, _, scene = data
    scenes, out = tmp_path / "scenes", tmp_path / "out"
    write_copies(scene, scenes)
    assert len(export_folder(scenes, root / "assets", out, "mjcf").written) == 3
    (out / "mine.txt").write_text("a user's own file")
    (scenes / "b.npz").unlink()
    (scenes / "c.npz").write_bytes(b"not a scene")
    report = export_folder(scenes, root / "assets", out, "mjcf")
    assert report.removed_stale == ["b.xml", "c.xml"] and list(report.failed) == ["c"]
    assert sorted(os.listdir(out)) == ["a.xml", "export.json", "mine.txt"]  # what export.json lists, and the user's
    saved = json.loads((out / "export.json").read_text())
    saved["written"] = {"x": str(tmp_path / "scenes" / "a.npz"), "y": str(out / "mine.txt"), "z": str(out / "export.json")}
    (out / "export.json").write_text(json.dumps(saved))  # a report naming files outside, or its own: nothing of them goes
    export_folder(scenes, root / "assets", out, "glb")
    assert (scenes / "a.npz").exists() and sorted(os.listdir(out)) == ["a.glb", "a.xml", "export.json", "mine.txt"]


def test_an_export_never_replaces_what_out_dir_held_that_no_export_there_wrote(data, tmp_path):
    root, _, scene = data
    scenes, out = tmp_path / "scenes", tmp_path / "out"
    write_copies(scene, scenes, ("assets", "notes"))  # ids whose outputs take the names of a user's folder and file
    (out / "assets").mkdir(parents=True)
    (out / "assets" / "mesh.obj").write_text("a user's mesh")
    (out / "notes").write_text("a user's notes")
    report = export_folder(scenes, root / "assets", out, "urdf")  # a folder per scene, named by its id
    assert (out / "assets" / "mesh.obj").read_text() == "a user's mesh"  # untouched (was moved aside and deleted)
    assert (out / "notes").read_text() == "a user's notes"
    assert sorted(report.written) == ["assets__assets", "notes__notes"]
    assert sorted(Path(k).name for k in report.duplicates) == ["assets.npz", "notes.npz"]
    assert all("no export there wrote" in why for why in report.duplicates.values())
    again = export_folder(scenes, root / "assets", out, "urdf")  # its own earlier outputs are replaced, as before
    assert sorted(again.written) == ["assets__assets", "notes__notes"] and again.duplicates == report.duplicates
    assert sorted(os.listdir(out)) == ["assets", "assets__assets", "export.json", "notes", "notes__notes"]
    assert (out / "assets" / "mesh.obj").exists() and (out / "notes").read_text() == "a user's notes"


def test_a_relaunch_after_a_killed_export_replaces_what_it_wrote_under_the_same_names(data, tmp_path, monkeypatch):
    """The outputs a killed export wrote were listed nowhere (export.json is written at the end), so the relaunch
    took them for a stranger's and exported those scenes again as ``<id>__<stem>``: export.json now notes them as
    they are written."""
    import spread.export as export

    root, _, scene = data
    scenes, out = tmp_path / "scenes", tmp_path / "out"
    write_copies(scene, scenes)
    real, calls = export.export_scene, []

    def killed_at_the_third(*args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(export, "export_scene", killed_at_the_third)
    with pytest.raises(KeyboardInterrupt):
        export_folder(scenes, root / "assets", out, "mjcf")
    assert sorted(os.listdir(out)) == ["a.xml", "b.xml", "export.json"]
    monkeypatch.setattr(export, "export_scene", real)
    report = export_folder(scenes, root / "assets", out, "mjcf")
    assert sorted(report.written) == ["a", "b", "c"] and not report.duplicates
    assert sorted(os.listdir(out)) == ["a.xml", "b.xml", "c.xml", "export.json"]
    assert "in_progress" not in json.loads((out / "export.json").read_text())


def test_export_command_refuses_an_out_dir_holding_a_dataset_or_a_run(data, tmp_path):
    root, _, _ = data
    proc = export_command(f"scenes={root / 'test'}", "format=mjcf", f"out_dir={root}", "progress=false")
    assert proc.returncode == 1 and f"out_dir={root}: holds a dataset" in proc.stderr, proc.stderr[-2000:]
    assert sorted(os.listdir(root)) == ["assets", "test"]  # nothing written beside the dataset


def test_a_sampling_runs_scenes_export_with_the_asset_library_of_the_dataset_they_were_sampled_from(data, tmp_path):
    from spread.export import assets_of

    root, _, scene = data
    run = tmp_path / "run"
    write_scene(scene, run / "scenes" / "a.npz")
    with pytest.raises(FileNotFoundError, match="give assets=DIR"):
        assets_of(run / "scenes", None)
    (run / "sampling.json").write_text(json.dumps({"fingerprint": {"data_root": str(root)}}))
    assert assets_of(run / "scenes", None) == root / "assets"
    report = export_folder(run / "scenes", assets_of(run / "scenes", None), run / "mjcf", "mjcf")
    assert list(report.written) == ["room|1"]
    # a damaged record is named with the refusal (the viewer's reader: spread.io.sampled_data), never a path
    (run / "sampling.json").write_text(json.dumps({"fingerprint": {"data_root": 7}}))
    with pytest.raises(FileNotFoundError, match=r"sampling\.json: 'fingerprint\.data_root' holds int 7, expected a "
                                                r"folder path \(text\)\); give assets=DIR"):
        assets_of(run / "scenes", None)


def export_command(*args: str) -> subprocess.CompletedProcess:
    """``spread-export`` (its Hydra main, run as a module so the test needs no installed console script)."""
    return subprocess.run([sys.executable, "-m", "spread.cli.export", *args], capture_output=True, text=True,
                          timeout=600, env={**os.environ, "HYDRA_FULL_ERROR": "1"})


def test_export_command_writes_every_scene(data, tmp_path):
    root, _, scene = data
    proc = export_command(f"scenes={root / 'test'}", "format=usd", f"out_dir={tmp_path / 'usd'}", "progress=false")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "1 scenes written as usd" in proc.stdout
    assert (tmp_path / "usd" / f"{safe_name(scene.scene_id)}.usda").exists()
    bad = export_command(f"scenes={root / 'test'}", "format=sdf", f"out_dir={tmp_path / 'x'}")
    assert bad.returncode != 0 and "format=sdf" in bad.stdout + bad.stderr


# ---- a generated room ---------------------------------------------------------------------------------------

@pytest.mark.slow
def test_generated_kitchen_exports_stand_in_pybullet_and_mujoco(tmp_path):
    from helpers import settled_room

    scene, library = settled_room(tmp_path / "kitchen")
    test_urdf_room_loads_in_pybullet_and_stays_put((None, library, scene), tmp_path / "urdf")
    test_mjcf_room_loads_in_mujoco_and_stays_put((None, library, scene), tmp_path / "mjcf")
