"""The Stability protocol's simulations (DESIGN §6): repeated jittered runs of one scene, and displacements.

One run: load the scene's bodies afresh (no contact cache carried over from an earlier run or scene),
place every object at its scene pose plus a translation jitter drawn uniformly from
[−jitter, +jitter]³ metres (rotations unchanged; wall and ceiling mounts, welded to the world by every
engine, are not jittered), all velocities zero, then simulate ``steps`` protocol
steps of ``dt`` seconds. Accuracy: each protocol step is made of ``substeps = round(dt / time_step)``
(at least 1) internal Bullet steps of ``dt / substeps`` — 4 steps of 1/240 s for the protocol's 1/60 s
with the default :class:`~spread.physics.params.PhysicsParams`. Jitters come from
``numpy.random.default_rng(seed)``, drawn at once as an array (runs, N, 3): the same seed gives the same
runs (bit for bit, in any process and whatever the world simulated before), different seeds differ.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Runs(NamedTuple):
    """Final Scene poses of every run: translation (runs, N, 3) metres, rotation (runs, N, 3, 3)."""

    translation: np.ndarray
    rotation: np.ndarray


class Displacement(NamedTuple):
    """Per-object motion between two pose sets: distance (..., N) metres the bbox centre moved, angle
    (..., N) radians of the relative rotation R_initialᵀ R_final."""

    distance: np.ndarray
    angle: np.ndarray


def protocol_substeps(dt: float, time_step: float) -> int:
    """Internal steps per protocol step of ``dt`` seconds, for a world whose step is ``time_step``."""
    return max(1, int(round(dt / time_step)))


def jitter_offsets(runs: int, num_objects: int, jitter: float, seed: int) -> np.ndarray:
    """(runs, N, 3) translation offsets, uniform in [−jitter, jitter] metres, from ``seed``."""
    return np.random.default_rng(seed).uniform(-jitter, jitter, size=(runs, num_objects, 3))


def simulate_runs(scene, library, runs: int = 10, steps: int = 100, dt: float = 1.0 / 60.0,
                  jitter: float = 5e-4, seed: int = 0, world=None) -> Runs:
    """Simulate ``runs`` jittered copies of ``scene`` for ``steps`` × ``dt`` seconds each (module docstring).

    ``world`` defaults to this process's :func:`~spread.physics.get_world`; its time step is restored after.
    A world with a ``simulate`` method (:class:`~spread.physics.mujoco_world.MujocoWorld`) gets all runs at
    once (same initial poses, same number of internal steps); any other world is run one run at a time.
    """
    if world is None:
        from spread.physics.worker import get_world

        world = get_world()
    n = scene.num_objects
    t0 = np.asarray(scene.translation, np.float64)
    R0 = np.asarray(scene.rotation, np.float64)
    from spread.scene import welded_objects

    offsets = jitter_offsets(runs, n, jitter, seed)
    offsets[:, welded_objects(scene)] = 0.0  # welded where the scene puts them
    out_t, out_R = np.zeros((runs, n, 3)), np.zeros((runs, n, 3, 3))
    substeps = protocol_substeps(dt, world.params.time_step)
    previous = world.time_step
    world.set_time_step(dt / substeps)
    try:
        if hasattr(world, "simulate"):  # an engine that steps the runs of a scene together (MujocoWorld)
            return Runs(*world.simulate(scene, library, t0 + offsets, R0, steps * substeps))
        for r in range(runs):
            world.load_scene(scene, library)
            world.set_poses(t0 + offsets[r], R0)
            world.step(steps * substeps)
            out_t[r], out_R[r] = world.poses()
    finally:
        world.set_time_step(previous)
    return Runs(out_t, out_R)


def displacement_stats(initial: tuple[np.ndarray, np.ndarray], final: tuple[np.ndarray, np.ndarray]) -> Displacement:
    """How far each object moved and turned from ``initial`` (t, R) to ``final`` (t, R).

    Shapes broadcast: initial (N, 3)/(N, 3, 3) against final (runs, N, 3)/(runs, N, 3, 3) gives (runs, N).
    The angle is computed as 2·asin(‖R_f − R_i‖_F / √8), exact and well-conditioned for small angles.
    """
    t_i, R_i = (np.asarray(a, np.float64) for a in initial)
    t_f, R_f = (np.asarray(a, np.float64) for a in final)
    distance = np.linalg.norm(t_f - t_i, axis=-1)
    chord = np.linalg.norm(R_f - R_i, axis=(-2, -1)) / np.sqrt(8.0)
    return Displacement(distance, 2.0 * np.arcsin(np.clip(chord, 0.0, 1.0)))
