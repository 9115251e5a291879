"""spread.physics: pybullet worlds from Scenes, on tiny libraries of boxes (known answers).

Sizes in metres. ``box`` is a 0.2 m cube, ``small`` a 0.1 m cube, ``L`` two box parts (centre of mass
off the bbox centre), ``U`` a concave trough of three box parts (its bottom's top face is 0.05 m above the
U's base, inner gap 0.4 m wide).
"""

from __future__ import annotations

import multiprocessing
import subprocess
import sys

import numpy as np
import pytest

from spread.assets.assemble import AssetSpec, box_asset, box_part, library_from_specs
from spread.physics import (
    BULLET_HULL_MARGIN, PhysicsParams, PhysicsWorld, displacement_stats, get_world, simulate_runs,
)
from spread.physics.frames import body_to_scene, matrix_to_quat, quat_to_matrix, scene_to_body
from spread.physics.shapes import inset_convex

from helpers import scene_of

pybullet = pytest.importorskip("pybullet")

PROTOCOL_STEP = 1.0 / 60.0


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _random_rotations(n: int, seed: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.random(n, random_state=seed).as_matrix()


def box_specs() -> list[AssetSpec]:
    """``box`` (0.2 m cube), ``small`` (0.1 m cube), ``L`` (two box parts, centre of mass off the bbox centre),
    ``U`` (a concave trough of three parts)."""
    u_parts = [box_part((0.5, 0.05, 0.2), (0, 0.025, 0)),
               box_part((0.05, 0.3, 0.2), (-0.225, 0.15, 0)), box_part((0.05, 0.3, 0.2), (0.225, 0.15, 0))]
    l_parts = [box_part((0.3, 0.1, 0.1), (0, 0.05, 0)), box_part((0.1, 0.3, 0.1), (-0.1, 0.15, 0))]
    return [box_asset("box", (0.2, 0.2, 0.2), category="box"), box_asset("small", (0.1, 0.1, 0.1), category="small"),
            AssetSpec("L", "L", 0, "object", l_parts, density=500.0),
            AssetSpec("U", "U", 0, "object", u_parts, density=300.0)]


def build_library(root):
    return library_from_specs(root, box_specs())


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    return build_library(tmp_path_factory.mktemp("physics_lib"))


@pytest.fixture(scope="module")
def world():
    with PhysicsWorld() as w:
        yield w


def run_steps(world: PhysicsWorld, protocol_steps: int) -> None:
    world.step(protocol_steps * round(PROTOCOL_STEP / world.time_step))


TOWER = [[0, 0.1, 0], [0, 0.3, 0], [0, 0.5, 0]]


# ---- resting, dropping, stacking -------------------------------------------------------------

def test_box_resting_on_floor_stays(world, library):
    scene = scene_of(["box"], [[0.3, 0.1, -0.2]], _rot_y(0.4)[None])
    world.load_scene(scene, library)
    run_steps(world, 100)
    moved = displacement_stats((scene.translation, scene.rotation), world.poses())
    assert moved.distance[0] < 1e-3 and moved.angle[0] < 1e-3


def test_dropped_box_comes_to_rest_on_floor(world, library):
    world.load_scene(scene_of(["box"], [[0, 0.1 + 0.1, 0]]), library)  # bottom 10 cm above the floor
    result = world.settle(max_steps=2400)
    assert result.settled
    assert abs(result.translation[0, 1] - 0.1) < 2e-3
    assert np.abs(result.translation[0, [0, 2]]).max() < 2e-3
    assert np.abs(world.velocities()[0]).max() < 5e-3


@pytest.mark.parametrize("pinned_base", [False, True])
def test_friction_coefficients_are_the_named_pairwise_values(world, library, pinned_base):
    # a box pushed at v0 slides v0² / (2 μ g) on the floor (μ = floor_friction) or on a pinned box (μ = friction)
    if pinned_base:
        world.load_scene(scene_of(["box", "small"], [[0, 0.1, 0], [0, 0.25, 0]]), library, fixed=[0])
        mu, v0 = world.params.friction, 0.5
    else:
        world.load_scene(scene_of(["small"], [[0, 0.05, 0]]), library)
        mu, v0 = world.params.floor_friction, 1.0
    world.step(10)
    start = world.poses()[0][-1, 0]
    pybullet.resetBaseVelocity(world.body_ids[-1], [v0, 0, 0], [0, 0, 0], physicsClientId=world.client)
    run_steps(world, 60)
    slid = world.poses()[0][-1, 0] - start
    assert slid == pytest.approx(v0 ** 2 / (2 * mu * 9.81), rel=0.1)


def test_exact_tower_is_stable_over_jittered_runs(world, library):
    scene = scene_of(["box"] * 3, TOWER)
    runs = simulate_runs(scene, library, runs=10, world=world)
    assert runs.translation.shape == (10, 3, 3) and runs.rotation.shape == (10, 3, 3, 3)
    moved = displacement_stats((scene.translation, scene.rotation), runs)
    assert moved.distance.max() < 3e-3 and moved.angle.max() < 1e-2


def test_tower_with_middle_box_shifted_half_a_width_topples(world, library):
    scene = scene_of(["box"] * 3, [[0, 0.1, 0], [0.1, 0.3, 0], [0, 0.5, 0]])
    runs = simulate_runs(scene, library, runs=3, world=world)
    top = displacement_stats((scene.translation, scene.rotation), runs)
    assert ((top.distance[:, 2] > 0.05) | (top.angle[:, 2] > 0.5)).all()


def test_tower_without_its_base_falls(world, library):
    scene = scene_of(["box"] * 2, TOWER[1:])
    runs = simulate_runs(scene, library, runs=2, world=world)
    drop = scene.translation[None, :, 1] - runs.translation[..., 1]
    assert (drop > 0.15).all()


def test_concave_asset_of_parts_holds_a_box_in_its_gap(world, library):
    # U base on the floor (bbox height 0.3 → centre 0.15); the small box starts inside the gap, 5 cm up
    scene = scene_of(["U", "small"], [[0, 0.15, 0], [0, 0.15, 0]])
    world.load_scene(scene, library)
    result = world.settle()
    assert result.settled
    # resting on the U's bottom part (top face y = 0.05), not on the convex hull's top (y = 0.3)
    assert abs(result.translation[1, 1] - (0.05 + 0.05)) < 2e-3
    assert abs(result.translation[0, 1] - 0.15) < 1e-3


def test_settle_with_pinned_furniture(world, library):
    # box 0 hangs in the air, pinned for the settle; box 1 falls onto it
    scene = scene_of(["box", "small"], [[0, 0.5, 0], [0, 0.8, 0]])
    world.load_scene(scene, library)
    result = world.settle(fixed=[0])
    assert result.settled
    assert np.allclose(result.translation[0], [0, 0.5, 0], atol=1e-9)
    assert abs(result.translation[1, 1] - (0.6 + 0.05)) < 2e-3
    assert world.frozen == []  # unpinned afterwards: it now falls
    run_steps(world, 30)
    assert world.poses()[0][0, 1] < 0.45


# ---- frames, shapes, contacts ------------------------------------------------------------------

def test_pose_round_trip_with_off_centre_mass_and_rotations(world, library):
    shape = world.body_shape(library, "L")
    assert np.linalg.norm(shape.com) > 0.03  # the L's centre of mass is far from its bbox centre
    n = 6
    t = np.random.default_rng(0).uniform(-1, 1, (n, 3)) + [0, 2, 0]
    R = _random_rotations(n, seed=1)
    scene = scene_of(["L", "box", "L", "U", "L", "small"], t, R)
    world.load_scene(scene, library)
    t_back, R_back = world.poses()
    assert np.abs(t_back - scene.translation).max() < 1e-6
    assert np.abs(R_back - scene.rotation).max() < 1e-6
    world.set_poses(t, R)  # float64 poses come back to round-off
    t_back, R_back = world.poses()
    assert np.abs(t_back - t).max() < 1e-9 and np.abs(R_back - R).max() < 1e-9
    # pybullet's base position is the centre of mass: t + R · com
    p, _ = pybullet.getBasePositionAndOrientation(world.body_ids[0], physicsClientId=world.client)
    assert np.allclose(p, t[0] + R[0] @ shape.com, atol=1e-9)


def test_frame_helpers_invert_each_other():
    R = _random_rotations(4, seed=3)
    assert np.allclose(quat_to_matrix(matrix_to_quat(R)), R, atol=1e-12)
    com, axes = np.random.default_rng(1).normal(size=(4, 3)), _random_rotations(4, seed=4)
    t = np.random.default_rng(2).normal(size=(4, 3))
    t2, R2 = body_to_scene(*scene_to_body(t, R, com, axes), com, axes)
    assert np.allclose(t2, t, atol=1e-12) and np.allclose(R2, R, atol=1e-12)


def test_parts_are_inset_by_bullets_margin():
    cube = box_part((0.2, 0.2, 0.2)).vertices
    inner = inset_convex(cube, BULLET_HULL_MARGIN)
    assert len(inner) == 8 and np.allclose(np.abs(inner), 0.1 - BULLET_HULL_MARGIN, atol=1e-12)
    board = box_part((0.3, 0.001, 0.3)).vertices  # 1 mm thin: inset by half its inradius (0.25 mm)
    assert np.allclose(np.abs(inset_convex(board, BULLET_HULL_MARGIN))[:, 1], 0.00025, atol=1e-9)


def test_shapes_created_once_per_asset_per_client(library):
    with PhysicsWorld() as w:
        w.load_scene(scene_of(["box", "box", "L"], [[0, 0.1, 0], [1, 0.1, 0], [2, 0.15, 0]]), library)
        assert w.shapes_created == 2
        w.load_scene(scene_of(["L", "small", "box"], [[0, 0.15, 0], [1, 0.05, 0], [2, 0.1, 0]]), library)
        assert w.shapes_created == 3 and w.num_objects == 3
        run_steps(w, 5)  # the shared shapes still simulate after the first scene's bodies were removed
        assert np.isfinite(w.poses()[0]).all()


def test_same_asset_id_from_another_library_gets_its_own_shape(library, tmp_path):
    bigger = library_from_specs(tmp_path, [box_asset("box", (0.4, 0.4, 0.4))])
    with PhysicsWorld() as w:
        w.load_scene(scene_of(["box"], [[0, 0.1, 0]]), library)
        w.load_scene(scene_of(["box"], [[0, 0.2, 0]]), bigger)  # keyed by content hash, not id alone
        assert w.shapes_created == 2
        run_steps(w, 30)
        assert abs(w.poses()[0][0, 1] - 0.2) < 1e-3


def test_contacts_report_support_between_stacked_boxes(world, library):
    world.load_scene(scene_of(["box"] * 2, TOWER[:2]), library)
    contacts = world.contacts(distance=1e-3)
    assert {tuple(p) for p in contacts.pairs()} == {(0, -1), (0, 1)}
    between = (contacts.index_a == 0) & (contacts.index_b == 1)
    assert np.allclose(np.abs(contacts.normal[between, 1]), 1.0, atol=1e-6)
    assert np.allclose(contacts.normal[contacts.index_b == -1], [0, 1, 0], atol=1e-6)
    assert np.abs(contacts.distance).max() < 1e-4  # exact parts: touching, no floating margin
    assert {tuple(p) for p in contacts.support_pairs()} == {(-1, 0), (0, 1)}
    run_steps(world, 10)  # after stepping the support carries the upper box's weight
    contacts = world.contacts(distance=1e-3)
    upper_weight = library["box"].mass * 9.81
    between = (contacts.index_a == 0) & (contacts.index_b == 1)
    assert contacts.normal_force[between].sum() == pytest.approx(upper_weight, rel=0.05)
    with pytest.raises(ValueError, match="contact_breaking_threshold"):
        world.contacts(distance=1.0)


def test_contacts_report_interpenetration(world, library):
    world.load_scene(scene_of(["box"] * 2, [[0, 0.1, 0], [0.15, 0.1, 0]]), library)  # 5 cm overlap in x
    contacts = world.contacts()
    pair = (contacts.index_a == 0) & (contacts.index_b == 1)
    assert contacts.penetration[pair].max() == pytest.approx(0.05, abs=2e-3)


# ---- the Stability protocol --------------------------------------------------------------------

def test_jittered_runs_repeat_with_a_seed_and_differ_across_seeds(world, library):
    scene = scene_of(["box", "box", "L"], TOWER[:2] + [[0.6, 0.15, 0]])
    a = simulate_runs(scene, library, runs=3, steps=30, seed=7, world=world)
    b = simulate_runs(scene, library, runs=3, steps=30, seed=7, world=world)
    c = simulate_runs(scene, library, runs=3, steps=30, seed=8, world=world)
    assert np.array_equal(a.translation, b.translation) and np.array_equal(a.rotation, b.rotation)
    assert np.abs(a.translation - c.translation).max() > 1e-5
    assert np.abs(a.translation[0] - a.translation[1]).max() > 1e-5  # runs within a call differ too
    with PhysicsWorld() as fresh:  # whatever a world simulated before, the runs are the same
        d = simulate_runs(scene, library, runs=3, steps=30, seed=7, world=fresh)
    assert np.array_equal(a.translation, d.translation)


def test_displacement_stats_known_answers():
    t0, R0 = np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1))
    t1 = np.array([[[0.03, 0.04, 0.0], [0, 0, 0]]])
    R1 = np.stack([np.eye(3), _rot_y(0.3)])[None]
    d = displacement_stats((t0, R0), (t1, R1))
    assert d.distance.shape == (1, 2) and np.allclose(d.distance, [[0.05, 0.0]])
    assert np.allclose(d.angle, [[0.0, 0.3]], atol=1e-12)


def _simulate_in_worker(root: str) -> np.ndarray:
    from spread.assets.library import AssetLibrary

    library = AssetLibrary.load(root)
    scene = scene_of(["box", "box", "small"], TOWER[:2] + [[0.5, 0.05, 0]])
    world = get_world(PhysicsParams())
    assert get_world() is world
    return simulate_runs(scene, library, runs=2, steps=20, seed=3).translation


def test_worker_processes_each_own_a_world_with_identical_results(library):
    ctx = multiprocessing.get_context("spawn")
    with ctx.Pool(2) as pool:
        results = pool.map(_simulate_in_worker, [str(library.root)] * 2)
    assert np.array_equal(results[0], results[1])
    assert np.array_equal(results[0], _simulate_in_worker(str(library.root)))


def test_get_world_is_cached_and_rebuilt_for_new_params():
    w = get_world()
    assert get_world() is w
    other = get_world(PhysicsParams(solver_iterations=20))
    assert other is not w and other.params.solver_iterations == 20
    assert get_world() is other  # no params: keep whatever this process has
    assert get_world(PhysicsParams()).params == PhysicsParams()


def test_import_does_not_pull_heavy_modules():
    code = "import sys, spread.physics; print('torch' in sys.modules, 'pybullet' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]
