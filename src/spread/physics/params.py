"""Named physics settings of a :class:`~spread.physics.world.PhysicsWorld` (SI units, y-up).

Friction as Bullet combines it: the coefficient of a contact is the *product* of the two bodies'
coefficients. The values here are the *pairwise* coefficients one wants (object–object and
object–floor); the world sets each object's own coefficient to √friction and the floor's to
floor_friction / √friction, so both products come out exactly as named.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Bullet gives every convex-hull collision shape this outward margin (metres), fixed for hulls read
#: from .obj files. Shapes are inset by it beforehand so that hull ⊕ margin matches the part (see shapes.py).
BULLET_HULL_MARGIN = 0.001


@dataclass(frozen=True)
class PhysicsParams:
    """Simulation settings; every field is in SI units.

    gravity: m/s², world frame (y-up).
    time_step: s, one internal Bullet step (``PhysicsWorld.step(1)``); protocol steps of 1/60 s are
        made of several of these (see ``spread.physics.runs.simulate_runs``).
    solver_iterations: sequential-impulse iterations per step (Bullet's ``numSolverIterations``).
    friction: Coulomb coefficient between two objects (pairwise, see module docstring).
    floor_friction: Coulomb coefficient between an object and the floor (pairwise).
    rolling_friction, spinning_friction: per-body coefficients (metres, Bullet's torsional model);
        small, so that round objects stop rolling without making boxes sticky.
    restitution: bounciness, 0 = perfectly inelastic (restitution is also multiplied pairwise).
    contact_breaking_threshold: m, Bullet keeps contact points up to this separation; also the largest
        ``distance`` that ``PhysicsWorld.contacts`` can report.
    allow_sleeping: let Bullet deactivate bodies at rest (off: every body is simulated every step,
        which keeps runs independent of sleep timers).
    sat_features: Bullet's separating-axis (polyhedral clipping) contacts between hulls. Off by default:
        with the margin-inset parts it misses exactly touching faces at load and lets a stable 3-box tower
        drift 4.5 mm in the protocol (GJK/EPA with contact persistence: 1.2 mm, the jitter's order).
    cone_friction: Bullet's implicit friction cone. Off by default: with y-up gravity it makes resting
        bodies creep diagonally (≈ 1 mm after a 10 cm drop, measured); the default friction pyramid
        does not.
    """

    gravity: tuple[float, float, float] = (0.0, -9.81, 0.0)
    time_step: float = 1.0 / 240.0
    solver_iterations: int = 50
    friction: float = 0.6
    floor_friction: float = 0.6
    rolling_friction: float = 1e-4
    spinning_friction: float = 1e-3
    restitution: float = 0.0
    contact_breaking_threshold: float = 0.02
    allow_sleeping: bool = False
    sat_features: bool = False
    cone_friction: bool = False
