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


@dataclass(frozen=True)
class MujocoParams:
    """MuJoCo settings of the Stability world (SI units). Chosen so the known answers hold
    (``tests/test_mujoco.py``) and measured against pybullet (benchmarks/RESULTS.md).

    gravity: m/s² along −up. time_step: s, one internal step (the protocol's 1/60 s is split into
        ``round(dt / time_step)`` of them, as for pybullet).
    integrator: ``implicitfast`` (stable with stiff contacts, MuJoCo's recommendation for rigid bodies).
    solver / iterations / tolerance: the constraint solver (Newton converges in a few iterations).
    cone: ``pyramidal`` friction cone, as Bullet's default friction pyramid.
    friction / floor_friction: Coulomb coefficient between two objects / an object and the floor. MuJoCo
        takes the larger of two geoms' coefficients; the floor has priority, so its value is used as is.
    torsional_friction / rolling_friction: m, used only with ``condim`` 4 / 6.
    condim: 3 = sliding friction only (MuJoCo's default).
    solref / solimp: MuJoCo's soft-contact reference (time constant s, damping ratio) and impedance. The
        time constant is half MuJoCo's default 0.02 s: measured on ground-truth rooms (benchmarks/RESULTS.md),
        0.02 s lets resting objects creep (1.7 % of objects moved ≥ 1 cm) where 0.01 s keeps them; a resting
        body sinks ≈ 0.1 mm into its support. MuJoCo raises it to 2 internal steps when the step is longer
        (``refsafe``), e.g. to 0.033 s with one internal step of 1/60 s.
    noslip_iterations: extra iterations of the no-slip solver (0: off).
    refsafe: MuJoCo raises a contact time constant below 2 internal steps to 2 steps (its default, on).
    multiccd: several contact points per pair of convex meshes (MuJoCo's default, on): flat faces rest
        on a face, not on one point.
    ccd_iterations / ccd_tolerance: the convex collision (GJK/EPA) iteration cap and tolerance, m.
    threads: threads that step one scene's runs together (``mujoco.rollout``); 1: a plain loop.
    sleep: MuJoCo's sleeping islands (MuJoCo ≥ 3.4): a group of touching bodies whose every velocity (angular
        ones times the body's size) stays under ``sleep_tolerance`` m/s for 10 internal steps is frozen and
        skipped by collision and solver until an awake body touches it. A run whose bodies are all asleep
        cannot change any more, so it ends there (:meth:`MujocoWorld.simulate`). With sleep on, runs are
        stepped one after another (``threads`` is not used: the sleep state is not part of a rollout's state).
    sleep_tolerance: m/s, MuJoCo's default 1e-3.
    """

    gravity: float = 9.81
    time_step: float = 1.0 / 240.0
    integrator: str = "implicitfast"
    solver: str = "Newton"
    iterations: int = 50
    tolerance: float = 1e-8
    cone: str = "pyramidal"
    friction: float = 0.6
    floor_friction: float = 0.6
    torsional_friction: float = 0.005
    rolling_friction: float = 1e-4
    condim: int = 3
    solref: tuple[float, float] = (0.01, 1.0)
    solimp: tuple[float, float, float, float, float] = (0.9, 0.95, 0.001, 0.5, 2.0)
    noslip_iterations: int = 0
    refsafe: bool = True
    multiccd: bool = True
    ccd_iterations: int = 35
    ccd_tolerance: float = 1e-6
    threads: int = 1
    sleep: bool = False
    sleep_tolerance: float = 1e-3
