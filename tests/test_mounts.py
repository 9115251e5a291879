"""Mount types (spread.scene: floor, on-object, wall, ceiling): stored in the scene file, read as today from
older files, and wall/ceiling objects welded to the world by every physics engine (a pendant lamp 2.5 m up
stays put; the same box without the mount falls)."""

from __future__ import annotations

import numpy as np
import pytest

from spread.metrics import scene_stability
from spread.scene import (
    MOUNT_CEILING, MOUNT_FLOOR, MOUNT_ON_OBJECT, MOUNT_WALL, SceneFormatError, read_scene, scene_mounts,
    welded_objects, write_scene,
)
from helpers import scene_of
from test_mujoco import build_box_library

pytest.importorskip("mujoco")


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    return build_box_library(tmp_path_factory.mktemp("mount_lib"))


def lamp_room(library, mounted: bool = True):
    """A cube on the floor, a cube 'pendant lamp' with its centre 2.5 m up (ceiling), a cup 1.5 m up on the
    wall, and a free cube 2.5 m up (it falls)."""
    scene = scene_of(["cube", "cube", "cup", "cube"],
                     [[0.0, 0.15, 0.0], [1.5, 2.5, 0.0], [-1.5, 1.5, 0.0], [0.0, 2.5, 1.5]], library=library,
                     posed_codes=True, scene_id="lamps")
    if mounted:
        scene.extras["mount"] = np.array([MOUNT_FLOOR, MOUNT_CEILING, MOUNT_WALL, MOUNT_FLOOR], np.int8)
    return scene


def test_mount_round_trips_and_older_files_read_from_the_support_graph(library, tmp_path):
    scene = lamp_room(library)
    back = read_scene(write_scene(scene, tmp_path / "a.npz"))
    assert scene_mounts(back).tolist() == [MOUNT_FLOOR, MOUNT_CEILING, MOUNT_WALL, MOUNT_FLOOR]
    assert welded_objects(back).tolist() == [False, True, True, False]
    old = lamp_room(library, mounted=False)
    old.physical[0, 3] = 1  # "0 supports 3"
    old = read_scene(write_scene(old, tmp_path / "old.npz"))
    assert scene_mounts(old).tolist() == [MOUNT_FLOOR, MOUNT_FLOOR, MOUNT_FLOOR, MOUNT_ON_OBJECT]
    assert not welded_objects(old).any()


def test_a_bad_mount_is_refused_naming_the_key(library, tmp_path):
    scene = lamp_room(library)
    scene.extras["mount"] = np.array([0, 3, 7, 0], np.int8)
    with pytest.raises(SceneFormatError, match="key 'mount'.*object 2 has mount code 7"):
        write_scene(scene, tmp_path / "bad.npz")


def assert_lamps_stay_and_the_free_cube_falls(world, library):
    result = scene_stability(lamp_room(library), library, runs=2, steps=60, world=world)
    moved = np.array(result.max_displacement)
    assert moved[1] == pytest.approx(0.0, abs=1e-6) and moved[2] == pytest.approx(0.0, abs=1e-6)
    assert moved[3] > 1.0  # 1 s of free fall from 2.5 m: on the floor
    free = scene_stability(lamp_room(library, mounted=False), library, runs=1, steps=60, world=world)
    assert free.max_displacement[1] > 1.0 and free.max_displacement[2] > 1.0  # unmounted, they fall


def test_pybullet_welds_wall_and_ceiling_mounts(library):
    from spread.physics import PhysicsWorld

    with PhysicsWorld() as world:
        assert_lamps_stay_and_the_free_cube_falls(world, library)
        world.load_scene(lamp_room(library), library)
        world.unfreeze()  # releasing pinned objects leaves the welded ones welded
        assert world.frozen == [1, 2]


def test_mujoco_welds_wall_and_ceiling_mounts_and_rebuilds_the_model_when_they_move(library):
    from spread.physics import MujocoWorld

    with MujocoWorld() as world:
        assert_lamps_stay_and_the_free_cube_falls(world, library)
        scene = lamp_room(library)
        world.load_scene(scene, library)
        assert world.model.nq == 7 * 2  # the two free cubes only
        compiled = world.models_compiled
        world.load_scene(lamp_room(library), library)
        assert world.models_compiled == compiled  # same bodies, same welds: reused
        scene.translation[1, 0] += 0.5
        world.load_scene(scene, library)
        assert world.models_compiled == compiled + 1  # a weld moved: the model is rebuilt
        t, _ = world.poses()
        assert np.allclose(t[1], scene.translation[1])


@pytest.mark.slow
def test_mujoco_warp_welds_wall_and_ceiling_mounts(library):
    pytest.importorskip("mujoco_warp")
    from spread.physics import MujocoWarpParams, MujocoWarpWorld

    with MujocoWarpWorld(MujocoWarpParams(device="auto")) as world:
        assert_lamps_stay_and_the_free_cube_falls(world, library)


def test_gravity_guidance_pulls_a_free_lamp_down_and_leaves_a_ceiling_lamp_alone():
    import tempfile

    import torch
    from test_guidance import SIZES, guide, run_steps, state

    from spread.assets.assemble import box_asset, library_from_specs

    with tempfile.TemporaryDirectory() as tmp:
        lib = library_from_specs(tmp, [box_asset(name, size) for name, size in SIZES.items()])
        x0 = state([[0.0, 0.1, 0.0], [1.0, 2.0, 0.5]])[None].float()  # a block on the floor, a "lamp" 2 m up
        free = run_steps(guide(lib, ["block", "crate"]), x0, 20)
        held = run_steps(guide(lib, ["block", "crate"], welded=torch.tensor([[False, True]])), x0, 20)
    assert free[0, 1, 1] < x0[0, 1, 1] - 0.01  # gravity pulls the unmounted one down (normalised y)
    assert torch.equal(held[0, 1], x0[0, 1])  # the mounted one stays


def test_asd_leaves_out_pairs_whose_supported_object_is_mounted(library):
    from spread.metrics.support_distance import scene_support_distance

    scene = lamp_room(library)
    scene.physical[0, 1] = 1  # "the floor cube supports the ceiling lamp": a 2 m gap, were it resting
    scene.physical[0, 3] = 1  # the free cube 2.2 m above its supporter
    result = scene_support_distance(scene, library)
    assert [(p.supporter, p.supported) for p in result.pairs] == [(0, 3)]
    assert result.pairs[0].min_signed_distance > 2.0


# ---- a 3D-FRONT-format room with lamps, imported -------------------------------------------------------

LAMP_CLASSES = ["desk", "pendant_lamp", "ceiling_lamp", "box", "start", "end"]


def front_room_with_lamps(root):
    """(src, splits): three InstructScene-layout rooms (boxes stand in for 3D-FUTURE models): a desk, a box
    on it, a pendant lamp with its centre 2.5 m up and a flat ceiling lamp at 2.75 m."""
    import json

    sizes = np.array([[0.5, 0.375, 0.3], [0.2, 0.3, 0.2], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1]])  # half extents
    rows = []
    for k in range(3):
        T = np.array([[0.0, 0.375, 0.0], [1.2, 2.5, 0.4 * k], [-1.0, 2.75, 0.5], [0.1, 0.85, 0.0]])
        tag = f"{k:04d}bbbb-house_Bedroom-{200 + k}"
        (root / tag).mkdir(parents=True)
        np.savez(root / tag / "boxes.npz", class_labels=np.eye(len(LAMP_CLASSES))[[0, 1, 2, 3]].astype(np.float32),
                 translations=T.astype(np.float32), sizes=sizes.astype(np.float32),
                 angles=np.zeros((4, 1), np.float32), jids=np.array([f"j{i}" for i in range(4)]))
        rows.append(f"Bedroom-{200 + k},{'test' if k == 2 else 'train'}")
    (root / "dataset_stats.txt").write_text(json.dumps({"class_labels": LAMP_CLASSES}))
    (root.parent / "splits.csv").write_text("\n".join(rows) + "\n")
    return root, root.parent / "splits.csv"


@pytest.fixture(scope="module")
def lamp_front(tmp_path_factory):
    from spread.assets import AssetLibrary
    from spread.importers.run import ImportConfig, import_dataset

    root = tmp_path_factory.mktemp("lamps")
    src, splits = front_room_with_lamps(root / "src")
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(root / "out"), splits=str(splits),
                                           room_type="bedroom", processes=1, progress=False, renders=0,
                                           decomposition="hull", fidelity_samples=0))
    scenes = [read_scene(p) for p in sorted((root / "out").glob("*/*.npz"))]
    return manifest, scenes, AssetLibrary.load(root / "out" / "assets")


def test_threed_front_lamps_are_ceiling_mounts_and_the_box_rests_on_the_desk(lamp_front):
    manifest, scenes, _ = lamp_front
    assert len(scenes) == 3
    for scene in scenes:
        assert scene_mounts(scene).tolist() == [MOUNT_FLOOR, MOUNT_CEILING, MOUNT_CEILING, MOUNT_ON_OBJECT]
    counts = manifest["room_counts"]
    assert (counts["mount_ceiling"], counts["mount_floor"], counts["mount_on_object"], counts["mount_wall"]) == (6, 3, 3, 0)


@pytest.mark.parametrize("engine", ["pybullet", "mujoco"])
def test_ground_truth_room_with_lamps_keeps_its_stability(lamp_front, engine):
    from spread.physics import MujocoWorld, PhysicsWorld

    _, scenes, library = lamp_front
    with (PhysicsWorld() if engine == "pybullet" else MujocoWorld()) as world:
        results = [scene_stability(sc, library, world=world) for sc in scenes]
        pooled = sum(sum(r.unchanged) for r in results) / sum(r.pairs * r.runs for r in results)
        assert pooled >= 0.98
        unmounted = scenes[0].with_poses(scenes[0].translation, scenes[0].rotation)
        del unmounted.extras["mount"]
        fallen = scene_stability(unmounted, library, runs=2, world=world)
        assert min(fallen.max_displacement[1:3]) > 1.0 and fallen.still_fraction <= 0.5  # without, the lamps fall


# ---- exports fix them ----------------------------------------------------------------------------------

def test_urdf_export_loads_mounts_with_a_fixed_base(library, tmp_path):
    import json

    import pybullet as pb

    from spread.export import export_scene
    from spread.export.urdf import load_urdf_scene, urdf_scene_poses

    scene = lamp_room(library)
    folder = export_scene(scene, library, tmp_path, "urdf")
    info = json.loads((folder / "scene.json").read_text())
    assert [o["fixed"] for o in info["objects"]] == [False, True, True, False]
    assert [o["mount"] for o in info["objects"]] == ["floor", "ceiling", "wall", "floor"]
    client = pb.connect(pb.DIRECT)
    try:
        bodies = load_urdf_scene(folder / "scene.json", client)
        for _ in range(240):
            pb.stepSimulation(physicsClientId=client)
        t, _ = urdf_scene_poses(bodies["objects"], client)
    finally:
        pb.disconnect(client)
    assert np.abs(t[1:3] - scene.translation[1:3]).max() < 1e-6  # the lamps stay
    assert t[3, 1] < 1.0  # the free cube fell


def test_mjcf_export_gives_mounts_no_joint(library, tmp_path):
    import mujoco

    from spread.export import export_scene

    scene = lamp_room(library)
    model = mujoco.MjModel.from_xml_path(str(export_scene(scene, library, tmp_path, "mjcf")))
    assert model.body_jntnum[1:].tolist() == [1, 0, 0, 1]
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    start = data.xpos[1:].copy()
    mujoco.mj_step(model, data, nstep=500)
    assert np.abs(data.xpos[2:4] - start[1:3]).max() < 1e-9 and data.xpos[4, 2] < start[3, 2] - 1.0  # z-up file


def test_usd_export_makes_mounts_kinematic(library, tmp_path):
    from pxr import Usd, UsdPhysics

    from spread.export import export_scene

    stage = Usd.Stage.Open(str(export_scene(lamp_room(library), library, tmp_path, "usd")))
    bodies = [p for p in stage.Traverse() if p.HasAPI(UsdPhysics.RigidBodyAPI)]
    assert [bool(UsdPhysics.RigidBodyAPI(b).GetKinematicEnabledAttr().Get()) for b in bodies] == [False, True, True,
                                                                                                   False]
    assert [b.GetAttribute("spread:mount").Get() for b in bodies] == ["floor", "ceiling", "wall", "floor"]


# ---- the model reads the mount ----------------------------------------------------------------------------

def test_the_denoiser_is_conditioned_on_each_objects_mount():
    import torch

    from spread.configs import model_config
    from spread.model.config import ModelConfig
    from spread.model.denoiser import GraphDenoiser

    cfg = model_config("tiny", dim=32, depth=1, heads=2, dim_head=8, edge_dim=16, index_dim=8, shape_dim=16)
    assert cfg.mount_feature  # new models have it
    assert not ModelConfig.from_any({"dim": 32}).mount_feature  # a checkpoint's config saved before it: off
    net = GraphDenoiser(cfg, geometry=False).eval()
    torch.nn.init.normal_(net.mount_in.weight)  # as after training (it starts at zero: no change at step 0)
    torch.nn.init.normal_(net.head[-1].weight)
    B, N = 1, 3
    args = (torch.randn(B, N, 9), torch.tensor([10]), torch.ones(B, N, dtype=torch.bool),
            torch.randn(B, N, N, 16), torch.randn(B, N, 4, 16))
    floor = torch.zeros(B, N, dtype=torch.long)
    ceiling = floor.clone()
    ceiling[0, 2] = MOUNT_CEILING
    with torch.no_grad():
        a, b = net(*args, mount=floor), net(*args, mount=ceiling)
    assert (a - b).abs().max() > 1e-4
    assert "mount_in.weight" not in GraphDenoiser(ModelConfig.from_any({"dim": 32, "heads": 2, "dim_head": 8}),
                                                  geometry=False).state_dict()


def test_samples_keep_their_graphs_mounts(library):
    from spread.sampling.worker import generated_scene

    class Item:
        name, k = "s0", 0
        graph = lamp_room(library)

    scene = generated_scene(Item.graph, Item.graph.translation, Item.graph.rotation, Item(), "test")
    assert scene_mounts(scene).tolist() == [MOUNT_FLOOR, MOUNT_CEILING, MOUNT_WALL, MOUNT_FLOOR]
