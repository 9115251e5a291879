"""A scene before and after one run of the Stability protocol's simulation, for pictures (DESIGN §6).

:func:`after_physics` runs :func:`spread.physics.simulate_runs` once with the protocol's settings — every
object dynamic, static floor, ``steps`` × ``dt`` seconds (100 × 1/60 s), a translation jitter of at most
``jitter`` metres per axis (0.5 mm) drawn from ``seed`` — in this process's physics world
(:func:`spread.physics.get_world`, whose internal step is the protocol's 1/240 s), and returns the scene at
its final poses together with how far each object moved and turned (bbox centre, metres; radians).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

#: The Stability protocol's run (spread.metrics.stability; restated here, render sits below metrics).
STEPS, DT, JITTER = 100, 1.0 / 60.0, 5e-4
#: An object counts as moved in a picture's caption beyond this many metres (the protocol's "still" bound).
MOVED = 0.01


@dataclass
class PhysicsOutcome:
    """before / after: the scene at its own and at its simulated poses; distance, angle (N,): motion of each
    object (metres, radians); steps, dt, jitter, seed: the run."""

    before: object
    after: object
    distance: np.ndarray
    angle: np.ndarray
    steps: int
    dt: float
    jitter: float
    seed: int

    @property
    def moved(self) -> int:
        """Objects whose bbox centre moved more than :data:`MOVED` metres."""
        return int((self.distance > MOVED).sum())

    def caption(self) -> str:
        if not len(self.distance):
            return "no objects"
        rate = 1.0 / self.dt
        step = f"1/{rate:.0f} s" if abs(rate - round(rate)) < 1e-6 else f"{self.dt:.4g} s"
        return (f"after {self.steps} steps of {step}: {self.moved}/{len(self.distance)} objects moved > "
                f"{MOVED * 100:.0f} cm, largest {self.distance.max() * 100:.1f} cm")


def after_physics(scene, library, steps: int = STEPS, dt: float = DT, jitter: float = JITTER, seed: int = 0,
                  world=None) -> PhysicsOutcome:
    """One Stability run of ``scene`` (module docstring)."""
    from spread.physics import displacement_stats, simulate_runs

    runs = simulate_runs(scene, library, runs=1, steps=steps, dt=dt, jitter=jitter, seed=seed, world=world)
    t, R = runs.translation[0], runs.rotation[0]
    moved = displacement_stats((scene.translation, scene.rotation), (t, R))
    after = replace(scene, translation=t.astype(np.float32), rotation=R.astype(np.float32),
                    extras=dict(scene.extras))
    return PhysicsOutcome(scene, after, moved.distance, moved.angle, int(steps), float(dt), float(jitter), int(seed))
