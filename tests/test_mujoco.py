"""spread.physics with MuJoCo: the MJCF of a scene, and the Stability protocol's known answers in MuJoCo.

Libraries of boxes as in ``test_physics`` (``box`` 0.2 m cube, ``small`` 0.1 m cube, ``L`` two box parts
with the centre of mass off the bbox centre, ``U`` a concave trough of three parts), plus ``table``
(1.0 × 0.75 × 0.6 box), ``cube`` (the 0.3 m cube of the metric tests' towers) and ``cup`` (a 16-sided
cylinder, radius 4 cm, 10 cm tall: a convex part that is not a box, so MuJoCo collides it as a mesh).
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from spread.assets.assemble import AssetSpec, box_asset, box_part, library_from_specs
from spread.metrics import scene_stability
from spread.physics import (
    MujocoParams, MujocoWorld, PhysicsParams, PhysicsWorld, displacement_stats, get_world, simulate_runs,
)
from spread.physics.mjcf import asset_geometry, cuboid, scene_mjcf
from spread.scene import Scene
from helpers import scene_of
from test_physics import box_specs

mujoco = pytest.importorskip("mujoco")

TOWER = [[0, 0.1, 0], [0, 0.3, 0], [0, 0.5, 0]]  # three 0.2 m boxes
TABLE_TOP = 0.75


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def cylinder_part(radius: float, height: float, sides: int = 16):
    import trimesh

    return trimesh.creation.cylinder(radius=radius, height=height, sections=sides,
                                     transform=trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))


def build_box_library(root):
    """The module's library (see the module docstring) under ``root``."""
    return library_from_specs(root, [
        *box_specs(),
        box_asset("cube", (0.3, 0.3, 0.3), category="cube"),
        box_asset("table", (1.0, TABLE_TOP, 0.6), category="dining_table", role="furniture"),
        AssetSpec("cup", "cup", 0, "object", [cylinder_part(0.04, 0.1)], density=400.0),
    ])


def settled_box_room(library, scene_id="settled") -> Scene:
    """A table with a box and a cup on it, a box in the U's gap, an L and a two-box tower on the floor: dropped a
    few millimetres and settled in pybullet, as the room generator does. No two centres on a sector boundary of
    the spatial codes (there sub-millimetre motion flips left/front)."""
    ids = ["table", "small", "cup", "U", "small", "L", "box", "box"]
    t = [[0, TABLE_TOP / 2, 0], [0.2, TABLE_TOP + 0.053, 0.1], [-0.3, TABLE_TOP + 0.053, -0.1], [1.2, 0.15, 0],
         [1.3, 0.103, 0], [-1.2, 0.153, 0.5], [0.3, 0.103, 1.2], [0.3, 0.306, 1.2]]
    R = np.stack([np.eye(3), _rot_y(0.3), np.eye(3), np.eye(3), np.eye(3), _rot_y(1.0), np.eye(3), _rot_y(0.2)])
    with PhysicsWorld() as pw:
        pw.load_scene(scene_of(ids, t, R, library=library, posed_codes=True), library)
        settled = pw.settle()
    assert settled.settled
    return scene_of(ids, settled.translation, settled.rotation, library=library, posed_codes=True, scene_id=scene_id)


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    return build_box_library(tmp_path_factory.mktemp("mujoco_lib"))


@pytest.fixture(scope="module", params=[False, True], ids=["awake", "sleeping"])
def world(request):
    """Every known answer holds with MuJoCo's sleeping islands off (the default) and on."""
    with MujocoWorld(MujocoParams(sleep=request.param)) as w:
        yield w


def protocol_steps(world, n: int) -> None:
    world.step(n * round((1 / 60) / world.time_step))


# ---- the MJCF: same bodies as pybullet --------------------------------------------------------------

def test_box_parts_become_box_geoms_and_other_parts_meshes(library):
    assert cuboid(box_part((0.3, 0.1, 0.2), (0.1, 0, 0)).vertices) is not None
    assert cuboid(cylinder_part(0.04, 0.1).vertices) is None
    assert len(asset_geometry(library, "U").box_centre) == 3 and not asset_geometry(library, "U").hulls
    cup = asset_geometry(library, "cup")
    assert len(cup.box_centre) == 0 and len(cup.hulls) == 1
    model = mujoco.MjModel.from_xml_string(scene_mjcf(scene_of(["U", "cup"], [[0, 0.15, 0], [1, 0.05, 0]],
                                                               library=library, posed_codes=True),
                                                      library))
    types = model.geom_type[model.geom_bodyid > 0]
    assert (types == mujoco.mjtGeom.mjGEOM_BOX).sum() == 3 and (types == mujoco.mjtGeom.mjGEOM_MESH).sum() == 1
    half = np.sort(model.geom_size[model.geom_bodyid == 1], axis=1)  # each box's half extents, any axis order
    assert sorted(map(tuple, np.round(half, 9))) == [(0.025, 0.1, 0.15), (0.025, 0.1, 0.15), (0.025, 0.1, 0.25)]


def test_bodies_have_the_pybullet_mass_inertia_and_centre_of_mass(world, library):
    t = np.array([[0, 1.0, 0], [1.0, 0.6, -0.5], [-1.0, 0.3, 0.4]])
    R = np.stack([_rot_y(0.3), np.eye(3), _rot_y(-1.2)])
    scene = scene_of(["L", "U", "cup"], t, R, library=library, posed_codes=True)
    world.load_scene(scene, library)
    with PhysicsWorld() as pw:
        pw.load_scene(scene, library)
        for i, aid in enumerate(scene.asset_id):
            shape = pw.body_shape(library, aid)
            assert world.model.body_mass[i + 1] == pytest.approx(library[aid].mass, rel=1e-12)
            assert np.allclose(world.model.body_inertia[i + 1], shape.inertia_per_kg * library[aid].mass, rtol=1e-6)
            com_bullet = pybullet_position(pw, i)
            assert np.allclose(world.data.xipos[i + 1], com_bullet, atol=1e-6)  # same centre of mass in the world


def pybullet_position(pw: PhysicsWorld, i: int) -> np.ndarray:
    import pybullet

    return np.asarray(pybullet.getBasePositionAndOrientation(pw.body_ids[i], physicsClientId=pw.client)[0])


def test_pose_round_trip_with_off_centre_mass_and_rotations(world, library):
    from scipy.spatial.transform import Rotation

    n = 5
    t = np.random.default_rng(0).uniform(-1, 1, (n, 3)) + [0, 2, 0]
    R = Rotation.random(n, random_state=1).as_matrix()
    scene = scene_of(["L", "box", "L", "U", "cup"], t, R, library=library, posed_codes=True)
    world.load_scene(scene, library)
    t_back, R_back = world.poses()
    assert np.abs(t_back - scene.translation).max() < 1e-6 and np.abs(R_back - scene.rotation).max() < 1e-6
    world.set_poses(t, R)
    t_back, R_back = world.poses()
    assert np.abs(t_back - t).max() < 1e-12 and np.abs(R_back - R).max() < 1e-12
    with pytest.raises(ValueError, match="5 objects"):
        world.set_poses(t[:2], R[:2])


def test_velocities_are_those_of_the_centre_of_mass(library):
    with MujocoWorld(MujocoParams(gravity=0.0)) as w:
        w.load_scene(scene_of(["L"], [[0, 2.0, 0]], _rot_y(0.7)[None], library=library, posed_codes=True), library)
        w.data.qvel[:] = [0.1, 0.0, -0.2, 0.5, -1.0, 3.0]  # free joint: body-origin velocity, local angular velocity
        mujoco.mj_forward(w.model, w.data)
        lin, ang = w.velocities()
        com0, R0 = w.data.xipos[1].copy(), w.data.xmat[1].reshape(3, 3).copy()
        w.step(1)
        mujoco.mj_forward(w.model, w.data)
        assert np.allclose(lin[0], (w.data.xipos[1] - com0) / w.time_step, rtol=0.02, atol=1e-4)
        assert np.allclose(ang[0], R0 @ [0.5, -1.0, 3.0], atol=1e-9)  # world frame


def test_z_up_export_is_the_same_room_turned(library):
    scene = scene_of(["table", "box"], [[0, TABLE_TOP / 2, 0], [0.2, TABLE_TOP + 0.1, 0.1]],
                     np.stack([np.eye(3), _rot_y(0.5)]), library=library, posed_codes=True)
    model = mujoco.MjModel.from_xml_string(scene_mjcf(scene, library, up="z", visual=True))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    yz = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]])  # y-up → z-up: (x, y, z) → (x, −z, y)
    assert np.allclose(data.xpos[1:], scene.translation @ yz.T, atol=1e-6)
    assert np.allclose(model.opt.gravity, [0, 0, -9.81])
    mujoco.mj_step(model, data, nstep=240)  # 1 s: the box stays on the table
    assert np.allclose(data.xpos[1:], scene.translation @ yz.T, atol=2e-3)


# ---- dynamics: resting, friction, stacking ------------------------------------------------------------

def test_box_resting_on_floor_stays_and_sinks_under_a_millimetre(world, library):
    scene = scene_of(["box"], [[0.3, 0.1, -0.2]], _rot_y(0.4)[None], library=library, posed_codes=True)
    world.load_scene(scene, library)
    protocol_steps(world, 100)
    moved = displacement_stats((scene.translation, scene.rotation), world.poses())
    assert moved.distance[0] < 1e-3 and moved.angle[0] < 1e-3
    assert 0 <= 0.1 - world.poses()[0][0, 1] < 1e-3


def test_dropped_cup_comes_to_rest_upright_on_the_floor(world, library):
    world.load_scene(scene_of(["cup"], [[0, 0.05 + 0.1, 0]], library=library, posed_codes=True), library)
    protocol_steps(world, 120)
    t, R = world.poses()
    assert abs(t[0, 1] - 0.05) < 1e-3 and np.abs(t[0, [0, 2]]).max() < 2e-3
    assert np.abs(world.velocities()[0]).max() < 5e-3


@pytest.mark.parametrize("on_box", [False, True])
def test_friction_coefficients_are_the_named_pairwise_values(world, library, on_box):
    # a small box pushed at v0 slides v0² / (2 μ g): on the floor (floor_friction) or on a wide base (friction)
    if on_box:
        scene = scene_of(["table", "small"], [[0, TABLE_TOP / 2, 0], [-0.3, TABLE_TOP + 0.05, 0]],
                         library=library, posed_codes=True)
        mu, v0 = world.params.friction, 1.0
    else:
        scene = scene_of(["small"], [[0, 0.05, 0]], library=library, posed_codes=True)
        mu, v0 = world.params.floor_friction, 1.0
    world.load_scene(scene, library)
    world.step(10)
    start = world.poses()[0][-1, 0]
    world.data.qvel[-6:] = [v0, 0, 0, 0, 0, 0]
    protocol_steps(world, 60)
    slid = world.poses()[0][-1, 0] - start
    assert slid == pytest.approx(v0 ** 2 / (2 * mu * 9.81), rel=0.1)


def test_exact_tower_is_stable_over_jittered_runs(world, library):
    scene = scene_of(["box"] * 3, TOWER, library=library, posed_codes=True)
    runs = simulate_runs(scene, library, runs=10, world=world)
    assert runs.translation.shape == (10, 3, 3) and runs.rotation.shape == (10, 3, 3, 3)
    moved = displacement_stats((scene.translation, scene.rotation), runs)
    assert moved.distance.max() < 3e-3 and moved.angle.max() < 1e-2


def test_tower_without_its_base_falls(world, library):
    scene = scene_of(["box"] * 2, TOWER[1:], library=library, posed_codes=True)
    runs = simulate_runs(scene, library, runs=2, world=world)
    assert (scene.translation[None, :, 1] - runs.translation[..., 1] > 0.15).all()


def test_concave_asset_of_parts_holds_a_box_in_its_gap(world, library):
    # the box starts in the gap
    scene = scene_of(["U", "small"], [[0, 0.15, 0], [0, 0.15, 0]], library=library, posed_codes=True)
    world.load_scene(scene, library)
    protocol_steps(world, 120)
    t, _ = world.poses()
    assert abs(t[1, 1] - (0.05 + 0.05)) < 2e-3  # on the U's bottom part, not on its hull's top (0.3)
    assert abs(t[0, 1] - 0.15) < 1e-3


# ---- the Stability metric's known answers ---------------------------------------------------------------

def cube_tower(library, shift=0.0, scene_id="tower"):
    return scene_of(["cube"] * 3, [[0, 0.15, 0], [shift, 0.45, 0], [0, 0.75, 0]], library=library, posed_codes=True,
                    scene_id=scene_id)


def test_cube_tower_is_stable(world, library):
    stable = scene_stability(cube_tower(library), library, world=world)
    assert stable.runs == 10 and stable.stability >= 0.98 and stable.still_fraction >= 0.98


def test_tower_shifted_by_two_thirds_of_a_cube_topples_in_every_run(world, library):
    # the top cube's centre is 5 cm past the middle cube's left edge and the middle cube's 5 cm past the bottom
    # one's right edge: the top falls left, then the middle right, in every run. Of the 6 ordered pairs only
    # top/bottom change ("above" → "left of"; top/middle stay "left of", middle/bottom "right of"): pybullet's
    # answer too (unchanged [4] * 10)
    toppled = scene_stability(cube_tower(library, shift=0.2), library, world=world)
    assert toppled.unchanged == [4] * 10 and toppled.still == [1] * 10
    assert toppled.max_displacement[2] > 0.3 and toppled.max_displacement[0] < 0.01  # the bottom is still


def test_tower_shifted_by_half_a_cube_balances_on_an_edge_and_topples_in_some_runs(world, library):
    # the top cube's centre is exactly over the middle cube's edge, the middle one's over the bottom one's: the
    # sub-millimetre jitter decides. pybullet (hull edges rounded by its 1 mm margin) collapses the tower in every
    # run (Stability 0.0); MuJoCo's sharp edges hold it in some runs (0.6 with this scene's seed).
    result = scene_stability(cube_tower(library, shift=0.15), library, world=world)
    assert result.stability < 0.9 and min(result.unchanged) < result.pairs
    assert max(result.max_displacement) > 0.1


@pytest.mark.parametrize("overhang, tips", [(0.03, False), (0.055, True)])
def test_cup_over_the_table_edge_tips_only_with_its_centre_past_the_edge(world, library, overhang, tips):
    # the table's edge is x = 0.5; the cup (radius 4 cm) reaches ``overhang`` past it
    x = 0.5 - 0.04 + overhang
    scene = scene_of(["table", "cup"], [[0, TABLE_TOP / 2, 0], [x, TABLE_TOP + 0.05, 0]], library=library,
                     posed_codes=True, scene_id=f"cup{overhang}")
    result = scene_stability(scene, library, world=world)
    if tips:  # centre of mass 1.5 cm past the edge: tips and falls off in every run
        assert result.still == [1] * 10 and result.max_rotation[1] > 0.5 and result.max_displacement[1] > 0.3
    else:  # centre 1 cm short of the edge: stays
        assert result.still == [2] * 10 and result.max_displacement[1] < 2e-3 and result.stability == 1.0


def test_box_above_a_smaller_box_with_its_centre_past_the_edge_tips_off_and_loses_its_relation(world, library):
    # the 0.2 m box stands on the 0.1 m box with its centre 3 cm past the small box's edge; it is "above" it (the
    # small box's centre is inside its footprint), tips off and lands beside it: both ordered pairs change
    scene = scene_of(["small", "box"], [[0, 0.05, 0], [0.08, 0.2, 0]], library=library, posed_codes=True,
                     scene_id="box_on_small")
    assert scene.spatial[1, 0] == 4  # above
    result = scene_stability(scene, library, world=world)
    assert result.unchanged == [0] * 10 and result.max_rotation[1] > 0.5


def assert_runs_repeat_differ_across_seeds_and_match(world, other, library, runs: int) -> None:
    """``world``'s runs repeat bit for bit with a seed and differ with another; ``other`` (the same model
    stepped another way) gives the same runs bit for bit."""
    scene = scene_of(["box", "box", "L", "cup"], TOWER[:2] + [[0.6, 0.15, 0], [-0.6, 0.05, 0.2]],
                     library=library, posed_codes=True)
    a = simulate_runs(scene, library, runs=runs, steps=30, seed=7, world=world)
    b = simulate_runs(scene, library, runs=runs, steps=30, seed=7, world=world)
    c = simulate_runs(scene, library, runs=runs, steps=30, seed=8, world=world)
    assert np.array_equal(a.translation, b.translation) and np.array_equal(a.rotation, b.rotation)
    assert np.abs(a.translation - c.translation).max() > 1e-5
    d = simulate_runs(scene, library, runs=runs, steps=30, seed=7, world=other)
    assert np.array_equal(a.translation, d.translation) and np.array_equal(a.rotation, d.rotation)


def test_runs_repeat_with_a_seed_differ_across_seeds_and_match_across_threads(world, library):
    with MujocoWorld(MujocoParams(threads=2, sleep=world.params.sleep)) as threaded:  # mujoco.rollout
        assert_runs_repeat_differ_across_seeds_and_match(world, threaded, library, runs=4)


def test_a_sleeping_box_is_woken_by_a_box_landing_on_it_and_pushed_as_when_awake(library):
    # the 0.1 m box rests on the floor; the 0.2 m box falls from 0.6 m onto its edge (centre 12 cm off), tips off
    # and shoves it ~5 mm. With sleep on, the small box falls asleep first, is woken by the impact, moves as in
    # the awake world and sleeps again
    scene = scene_of(["small", "box"], [[0, 0.05, 0], [0.12, 0.6, 0]], library=library, posed_codes=True)
    final, awake = {}, []
    for sleep in (False, True):
        with MujocoWorld(MujocoParams(sleep=sleep)) as w:
            w.load_scene(scene, library)
            for _ in range(60):
                protocol_steps(w, 1)
                awake.append(bool(w.data.body_awake[1])) if sleep else None
            final[sleep] = displacement_stats((scene.translation, scene.rotation), w.poses())
    assert not all(awake[:10]) and awake[20] and not awake[-1]  # asleep, woken by the impact, asleep again
    assert final[False].distance[0] > 3e-3
    assert abs(final[True].distance[0] - final[False].distance[0]) < 1e-3
    assert final[True].angle[1] > 1.0 and final[False].angle[1] > 1.0  # the big box tipped off in both


def test_sleeping_runs_of_a_settled_room_end_early_and_agree_with_awake_runs(library):
    scene = settled_box_room(library)
    runs = {}
    for sleep in (False, True):
        with MujocoWorld(MujocoParams(sleep=sleep)) as w:
            runs[sleep] = simulate_runs(scene, library, runs=4, world=w)
            runs[sleep, "steps"] = w.steps_simulated
    assert runs[False, "steps"] == 4 * 100 * 4 and runs[True, "steps"] < 0.5 * runs[False, "steps"]
    assert np.abs(runs[True].translation - runs[False].translation).max() < 1e-3
    moved = {k: displacement_stats((scene.translation, scene.rotation), runs[k]).distance for k in (False, True)}
    assert ((moved[True] < 0.01) == (moved[False] < 0.01)).all()


def assert_model_reused_for_new_poses_and_rebuilt_for_new_bodies(w, library) -> None:
    scene = scene_of(["box"] * 2, TOWER[:2], library=library, posed_codes=True)
    simulate_runs(scene, library, runs=3, steps=2, world=w)
    simulate_runs(scene.with_poses(scene.translation + 0.01, scene.rotation), library, runs=3, steps=2, world=w)
    assert w.models_compiled == 1
    simulate_runs(scene_of(["box", "small"], TOWER[:2], library=library, posed_codes=True), library, runs=1, steps=2,
                  world=w)
    assert w.models_compiled == 2


def test_a_loaded_scene_model_is_reused_for_its_runs(library):
    with MujocoWorld() as w:
        assert_model_reused_for_new_poses_and_rebuilt_for_new_bodies(w, library)


def test_get_world_picks_the_engine_from_the_params():
    assert isinstance(get_world(MujocoParams()), MujocoWorld)
    assert get_world() is get_world(MujocoParams())
    assert isinstance(get_world(PhysicsParams()), PhysicsWorld)


def test_protocol_physics_selects_the_engine():
    from spread.evaluation.protocol import EvalProtocol

    params = EvalProtocol(physics="mujoco", stability_substeps=2).physics_params()
    assert isinstance(params, MujocoParams) and params.time_step == pytest.approx(1 / 120)
    assert isinstance(EvalProtocol().physics_params(), PhysicsParams)
    assert EvalProtocol(physics="mujoco").to_dict()["physics_params"]["solver"] == "Newton"
    with pytest.raises(ValueError, match="protocol.physics"):
        EvalProtocol(physics="bullet")
    assert EvalProtocol(physics="mujoco", physics_sleep=True).physics_params().sleep
    assert not EvalProtocol(physics="mujoco").physics_params().sleep
    with pytest.raises(ValueError, match="physics_sleep.*pybullet"):
        EvalProtocol(physics_sleep=True)


def test_mujoco_cannot_pin_objects(world, library):
    with pytest.raises(NotImplementedError, match="settle"):
        world.load_scene(scene_of(["box"], [[0, 0.1, 0]], library=library, posed_codes=True), library, fixed=[0])


def test_import_does_not_pull_mujoco():
    code = "import sys, spread.physics, spread.physics.mjcf; print('mujoco' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split() \
        == ["False"]


# ---- settled rooms -------------------------------------------------------------------------------------

def test_room_settled_by_pybullet_stays_in_mujoco(world, library):
    result = scene_stability(settled_box_room(library), library, world=world)
    assert result.stability >= 0.99 and result.still_fraction >= 0.99
    assert max(result.max_displacement) < 3e-3


def test_room_settling_can_verify_with_mujoco(library):
    import spread.procgen.settle as settle

    T0 = np.array([[0, TABLE_TOP / 2 + 0.002, 0], [0.2, TABLE_TOP + 0.055, 0.1]])
    keep, T, R, rel, report = settle.settle_room(["table", "small"], ["dining_table", "small"], ["furniture", "object"],
                                                 [None, 0], T0, np.tile(np.eye(3), (2, 1, 1)), library,
                                                 settle.SettleConfig(verify_physics="mujoco"))
    assert list(keep) == [0, 1] and rel.codes[0, 1] == 1  # the table supports the box
    assert settle._MUJOCO is not None and settle._MUJOCO.models_compiled >= 1  # the verification ran in MuJoCo
    with pytest.raises(ValueError, match="verify_physics"):
        settle.SettleConfig(verify_physics="bullet")


@pytest.fixture(scope="module")
def kitchen(tmp_path_factory):
    from helpers import settled_room

    return settled_room(tmp_path_factory.mktemp("mujoco_room"))


@pytest.mark.slow
def test_generated_kitchen_stays_in_mujoco(kitchen):
    scene, library = kitchen
    result = scene_stability(scene, library, world=MujocoWorld())
    assert result.stability >= 0.99 and result.still_fraction >= 0.99


def test_a_diverging_simulation_raises_instead_of_looking_still(library):
    # MuJoCo's default would reset a diverged simulation to its start, which reads as "nothing moved"
    scene = scene_of(["box"], [[0, 0.1, 0]], library=library, posed_codes=True)
    with MujocoWorld(MujocoParams(gravity=float("nan"))) as w, pytest.raises(FloatingPointError, match="diverged"):
        simulate_runs(scene, library, runs=2, steps=5, world=w)
