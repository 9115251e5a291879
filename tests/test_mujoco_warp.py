"""spread.physics with MuJoCo Warp: a scene's runs as one batch of worlds, the known answers, and agreement with C
MuJoCo on the same runs (on the CPU here: Warp's CPU device is deterministic).

The box library and scenes are those of ``test_mujoco``. Stepping tests are ``slow``: on a machine whose Warp
kernel cache (``~/.cache/warp``) is cold the first step compiles MJWarp's kernels for about a minute on one
core; with the cache warm this file's slow tests take about a minute in all (10 worlds × 400 steps of a few
bodies cost ~4 s on this CPU). The fast tests build worlds and models but never step.
"""

from __future__ import annotations

import logging
import subprocess
import sys

import numpy as np
import pytest

from spread.metrics import STILL_ANGLE, STILL_DISTANCE, scene_stability
from spread.physics import (
    MujocoParams, MujocoWarpParams, MujocoWarpWorld, MujocoWorld, PhysicsParams, displacement_stats, get_world,
    simulate_runs,
)

pytest.importorskip("mujoco")
mjw = pytest.importorskip("mujoco_warp")

from helpers import scene_of  # noqa: E402
from test_mujoco import (  # noqa: E402
    TOWER, assert_model_reused_for_new_poses_and_rebuilt_for_new_bodies,
    assert_runs_repeat_differ_across_seeds_and_match, build_box_library, cube_tower, settled_box_room,
)

CPU = MujocoWarpParams(device="cpu")


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    return build_box_library(tmp_path_factory.mktemp("warp_lib"))


@pytest.fixture(scope="module")
def world():
    with MujocoWarpWorld(CPU) as w:
        yield w


def still(scene, runs) -> np.ndarray:
    moved = displacement_stats((scene.translation, scene.rotation), runs)
    return (moved.distance < STILL_DISTANCE) & (moved.angle < STILL_ANGLE)


# ---- fast: settings, engine choice, buffers (no stepping) ------------------------------------------------

def test_protocol_physics_mujoco_warp_selects_the_batched_engine():
    from spread.evaluation.protocol import EvalProtocol

    params = EvalProtocol(physics="mujoco_warp", stability_substeps=2).physics_params()
    assert type(params) is MujocoWarpParams and params.time_step == pytest.approx(1 / 120)
    record = EvalProtocol(physics="mujoco_warp").to_dict()["physics_params"]
    assert record["solver"] == "Newton" and record["device"] == "auto"
    world = get_world(CPU)
    assert isinstance(world, MujocoWarpWorld) and world.device == "cpu"
    assert isinstance(get_world(MujocoParams()), MujocoWorld)  # a MujocoWarpParams is not a MujocoParams' equal
    assert not isinstance(get_world(MujocoParams()), MujocoWarpWorld)
    get_world(PhysicsParams())


@pytest.mark.parametrize("bad, match", [(dict(device="gpu"), "device"), (dict(nconmax=0), "nconmax"),
                                        (dict(njmax=-1), "njmax"), (dict(overflow_retries=-1), "overflow_retries")])
def test_bad_warp_settings_are_refused_by_name(bad, match):
    with pytest.raises(ValueError, match=match):
        MujocoWarpParams(**bad)


def test_asking_for_cuda_without_a_gpu_says_so():
    import warp as wp

    if wp.is_cuda_available():
        pytest.skip("this machine has a CUDA device")
    with pytest.raises(RuntimeError, match="no CUDA device"):
        MujocoWarpWorld(MujocoWarpParams(device="cuda"))
    assert MujocoWarpWorld(MujocoWarpParams(device="auto")).device == "cpu"


def test_the_device_model_is_the_c_model_of_the_same_mjcf(world, library):
    scene = scene_of(["L", "U", "cup"], [[0, 1.0, 0], [1.0, 0.6, -0.5], [-1.0, 0.3, 0.4]],
                     library=library, posed_codes=True)
    world.load_scene(scene, library)
    with MujocoWorld() as c:
        c.load_scene(scene, library)
        for field in ("body_mass", "body_inertia", "body_ipos", "geom_size", "geom_type"):
            assert np.allclose(getattr(world.model, field).numpy().reshape(getattr(c.model, field).shape),
                               getattr(c.model, field), rtol=1e-6), field
    assert world.model.opt.cone == mjw.ConeType.PYRAMIDAL and world.model.opt.solver == mjw.SolverType.NEWTON


def test_buffers_grow_with_the_contacts_of_the_scene(world, library):
    # in the air: no contact
    world.load_scene(scene_of(["box"], [[0, 1.0, 0]], library=library, posed_codes=True), library)
    alone = world.buffers(scene_of(["box"], [[0, 1.0, 0]], library=library, posed_codes=True))
    tower = scene_of(["box"] * 3, TOWER, library=library, posed_codes=True)
    world.load_scene(tower, library)
    stacked = world.buffers(tower)
    assert alone == (8 + 16, 4 * (8 + 16))  # no contact: 8 per object and 16
    assert stacked[0] > 3 * 8 + 16 and stacked[1] == 4 * stacked[0]  # 3 objects plus twice the resting contacts


def test_import_does_not_pull_warp():
    code = "import sys, spread.physics; print('warp' in sys.modules, 'mujoco_warp' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split() \
        == ["False", "False"]


# ---- slow: stepping (kernel compile on a cold cache) -------------------------------------------------------

@pytest.mark.slow
def test_box_resting_on_floor_stays_in_every_world(world, library):
    scene = scene_of(["box"], [[0.3, 0.1, -0.2]], library=library, posed_codes=True)
    runs = simulate_runs(scene, library, runs=4, world=world)
    moved = displacement_stats((scene.translation, scene.rotation), runs)
    assert runs.translation.shape == (4, 1, 3) and moved.distance.max() < 1e-3 and moved.angle.max() < 1e-3
    assert (world.last_overflow == 0).all()


@pytest.mark.slow
def test_cube_tower_stands_and_the_tower_shifted_by_two_thirds_falls(world, library):
    stable = scene_stability(cube_tower(library), library, world=world)
    assert stable.runs == 10 and stable.stability >= 0.98 and stable.still_fraction >= 0.98
    toppled = scene_stability(cube_tower(library, shift=0.2), library, world=world)
    assert toppled.unchanged == [4] * 10 and toppled.still == [1] * 10  # C MuJoCo's and pybullet's answer
    assert toppled.max_displacement[2] > 0.3 and toppled.max_displacement[0] < 0.01


@pytest.mark.slow
def test_runs_agree_with_c_mujoco_on_a_settled_room(world, library):
    # the same model and runs (same jitter), float32 MJWarp against float64 C MuJoCo, box-box pairs through the same
    # collider (measured: 1.3 µm, 3e-5 in R). The bound is float32 round-off of metre-sized positions (1e-7)
    # carried through 4,000 steps of stiff contacts, with a margin; GJK/EPA box-box contacts (MJWarp's default)
    # would differ by the way resting boxes sit in their soft contacts
    scene = settled_box_room(library)
    warp = simulate_runs(scene, library, runs=10, world=world)
    with MujocoWorld() as c:
        ref = simulate_runs(scene, library, runs=10, world=c)
    assert np.abs(warp.translation - ref.translation).max() < 1e-4
    assert np.abs(warp.rotation - ref.rotation).max() < 1e-3
    assert (still(scene, warp) == still(scene, ref)).all() and still(scene, warp).all()


@pytest.mark.slow
def test_falling_runs_end_like_c_mujoco(world, library):
    # a box with its centre past a smaller box's edge tips off and lands beside it, in both engines at the same place
    # (measured: 1.5 µm apart). A fall amplifies round-off (in generated rooms a toppling book ends up to 17 cm
    # apart, benchmarks/RESULTS.md), so the bound here is the still/moved decision and 1 mm
    scene = scene_of(["small", "box"], [[0, 0.05, 0], [0.08, 0.2, 0]], library=library, posed_codes=True)
    warp = simulate_runs(scene, library, runs=4, world=world)
    with MujocoWorld() as c:
        ref = simulate_runs(scene, library, runs=4, world=c)
    assert (still(scene, warp) == still(scene, ref)).all() and not still(scene, warp)[:, 1].any()
    assert np.abs(warp.translation - ref.translation).max() < 1e-3


@pytest.mark.slow
def test_runs_repeat_bit_for_bit_on_cpu_with_or_without_graph_replay_and_differ_across_seeds(world, library):
    with MujocoWarpWorld(MujocoWarpParams(device="cpu", graph_capture=False)) as direct:  # launched from Python
        assert_runs_repeat_differ_across_seeds_and_match(world, direct, library, runs=3)


@pytest.mark.slow
def test_overflowing_contact_buffers_are_grown_and_the_batch_rerun(library, caplog):
    scene = scene_of(["box"] * 3, TOWER, library=library, posed_codes=True)
    with MujocoWarpWorld(CPU) as w:
        ref = simulate_runs(scene, library, runs=2, steps=20, world=w)
    tiny = MujocoWarpParams(device="cpu", nconmax=2, njmax=8, overflow_retries=4)
    with MujocoWarpWorld(tiny) as w, caplog.at_level(logging.WARNING, "spread.physics.warp"):
        grown = simulate_runs(scene, library, runs=2, steps=20, world=w)
    assert "overflowed" in caplog.text and w._buffers[0] > 2
    assert np.array_equal(grown.translation, ref.translation)  # the kept batch is one that did not overflow
    with MujocoWarpWorld(MujocoWarpParams(device="cpu", nconmax=2, njmax=8, overflow_retries=0)) as w, \
            pytest.raises(RuntimeError, match="overflowed its buffers .*nconmax=2, njmax=8"):
        simulate_runs(scene, library, runs=2, steps=20, world=w)


@pytest.mark.slow
def test_a_diverging_simulation_raises_instead_of_returning_nan(library):
    scene = scene_of(["box"], [[0, 0.1, 0]], library=library, posed_codes=True)
    with MujocoWarpWorld(MujocoWarpParams(device="cpu", gravity=float("nan"))) as w, \
            pytest.raises(FloatingPointError, match="diverged"):
        simulate_runs(scene, library, runs=2, steps=5, world=w)


@pytest.mark.slow
def test_a_loaded_scene_model_is_reused_for_its_runs(library):
    with MujocoWarpWorld(CPU) as w:
        assert_model_reused_for_new_poses_and_rebuilt_for_new_bodies(w, library)
