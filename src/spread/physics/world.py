"""A pybullet world built from Scenes: one DIRECT client, a static floor, one rigid body per object.

Made to be reused: a worker process keeps one :class:`PhysicsWorld` (see :func:`spread.physics.get_world`)
and loads scene after scene into it. Collision shapes are created once per asset per client and shared by
every body of that asset in every scene; switching scenes removes the scene's bodies (``removeBody``),
never ``resetSimulation`` (which would drop the cached shapes).

Frames: world is y-up, metres, floor the plane y = 0. Poses in and out are the Scene's (bbox-centre
translation, world-from-local rotation); inside, a body's frame is its asset's centre of mass and
principal axes of inertia (see :mod:`spread.physics.shapes` and :mod:`spread.physics.frames`).
Bodies are Bullet rigid bodies (``useMaximalCoordinates``): the fastest kind for free single-link
objects, and the only kind whose mass can be set to 0 (static) and back, which :meth:`freeze` uses.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
import weakref
from dataclasses import dataclass
from typing import Iterable

import numpy as np

from spread.physics.contacts import FLOOR, ContactSet, contact_set
from spread.physics.frames import body_to_scene, scene_to_body
from spread.physics.params import BULLET_HULL_MARGIN, PhysicsParams
from spread.physics.shapes import BodyShape, asset_mass_frame, body_parts, write_parts_obj
from spread.physics.engines import EngineSpec, register_engine


@dataclass
class SettleResult:
    """Outcome of :meth:`PhysicsWorld.settle`: final Scene poses (N, 3) / (N, 3, 3), internal steps taken,
    and whether every body came to rest (False: ``max_steps`` ran out first)."""

    translation: np.ndarray
    rotation: np.ndarray
    steps: int
    settled: bool


def _close_client(pb, client: int) -> None:
    if pb.isConnected(physicsClientId=client):
        pb.disconnect(physicsClientId=client)


class PhysicsWorld:
    """One pybullet DIRECT client with gravity (y-up), a floor at y = 0, and the bodies of one scene.

    ``shapes_created`` counts collision shapes created for assets on this client (one per asset, ever).
    Not thread-safe: one thread uses a world at a time.
    """

    def __init__(self, params: PhysicsParams | None = None):
        import pybullet

        self._pb = pybullet
        self.params = params or PhysicsParams()
        self.client = pybullet.connect(pybullet.DIRECT)
        if self.client < 0:
            raise RuntimeError("pybullet: could not open a DIRECT client")
        self._tmpdir: str | None = None  # made only for assets of a read-only library
        self._finalizer = weakref.finalize(self, _close_client, pybullet, self.client)
        self.shapes_created = 0
        self._shapes: dict[tuple[str, str], BodyShape] = {}
        self._bodies: list[int] = []
        self._com = np.zeros((0, 3))
        self._axes = np.zeros((0, 3, 3))
        self._mass = np.zeros(0)
        self._inertia = np.zeros((0, 3))
        self._frozen: set[int] = set()
        self.time_step = self.params.time_step
        self._configure()
        self.floor_id = self._create_floor()

    # ---- setup -------------------------------------------------------------------------------
    def _call(self, name: str, *args, **kwargs):
        return getattr(self._pb, name)(*args, physicsClientId=self.client, **kwargs)

    def _configure(self) -> None:
        p = self.params
        self._call("setGravity", *p.gravity)
        self._call("setTimeStep", p.time_step)
        self._call("setPhysicsEngineParameter", numSolverIterations=int(p.solver_iterations),
                   deterministicOverlappingPairs=1, contactBreakingThreshold=float(p.contact_breaking_threshold),
                   enableFileCaching=0, enableSAT=int(p.sat_features),
                   enableConeFriction=int(p.cone_friction))

    def _create_floor(self) -> int:
        pb, p = self._pb, self.params
        shape = self._call("createCollisionShape", pb.GEOM_PLANE, planeNormal=[0.0, 1.0, 0.0])
        floor = self._call("createMultiBody", baseMass=0.0, baseCollisionShapeIndex=shape)
        self._call("changeDynamics", floor, -1, lateralFriction=p.floor_friction / self._object_friction,
                   restitution=p.restitution, rollingFriction=p.rolling_friction,
                   spinningFriction=p.spinning_friction)
        return floor

    @property
    def _object_friction(self) -> float:
        return math.sqrt(self.params.friction)

    def close(self) -> None:
        """Disconnect the client (also done at garbage collection)."""
        self._finalizer()

    def __enter__(self) -> "PhysicsWorld":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ---- shapes ------------------------------------------------------------------------------
    def body_shape(self, library, asset_id: str) -> BodyShape:
        """The asset's collision shape and mass frame on this client, created on first use."""
        record = library[asset_id]
        key = (str(asset_id), record.content_hash)
        shape = self._shapes.get(key)
        if shape is None:
            com, axes, inertia_per_kg = asset_mass_frame(library, asset_id)
            path = self._shape_file(library, asset_id,
                                    lambda: body_parts(library.convex_parts(asset_id), com, axes))
            flags = self._pb.URDF_INITIALIZE_SAT_FEATURES if self.params.sat_features else 0
            # the file stays until close(): pybullet reads it again for each body's (unused) visual shape
            cid = self._call("createCollisionShape", self._pb.GEOM_MESH, fileName=path, flags=flags)
            if cid < 0:
                raise RuntimeError(f"pybullet could not create the collision shape of asset '{asset_id}'")
            self.shapes_created += 1
            shape = self._shapes[key] = BodyShape(cid, com, axes, inertia_per_kg)
        return shape

    def _shape_file(self, library, asset_id: str, make_parts) -> str:
        """The OBJ compound pybullet loads for an asset: kept in the library's cache folder, keyed by
        the asset's content hash (written once, shared by every process); in this world's temporary
        folder when the library is read-only."""
        record = library[asset_id]
        name = f"{asset_id}.{record.content_hash[:16]}.physics-{round(BULLET_HULL_MARGIN * 1e6)}um.obj"
        cached = os.path.join(str(library.root), "cache", name)
        if os.path.exists(cached):
            return cached
        try:
            os.makedirs(os.path.dirname(cached), exist_ok=True)
            tmp = f"{cached}.{os.getpid()}.tmp"
            write_parts_obj(tmp, make_parts())
            os.replace(tmp, cached)
            return cached
        except OSError:
            if self._tmpdir is None:
                self._tmpdir = tempfile.mkdtemp(prefix="spread-physics-")
                weakref.finalize(self, shutil.rmtree, self._tmpdir, True)
            path = os.path.join(self._tmpdir, f"shape{self.shapes_created}.obj")
            write_parts_obj(path, make_parts())
            return path

    # ---- scenes ------------------------------------------------------------------------------
    @property
    def num_objects(self) -> int:
        return len(self._bodies)

    @property
    def body_ids(self) -> list[int]:
        """pybullet body ids of the loaded objects, in scene order."""
        return list(self._bodies)

    def clear(self) -> None:
        """Remove the current scene's bodies (the floor and the cached shapes stay)."""
        for body in self._bodies:
            self._call("removeBody", body)
        self._bodies = []
        self._frozen = set()
        self._welded = set()
        self._com, self._axes = np.zeros((0, 3)), np.zeros((0, 3, 3))
        self._mass, self._inertia = np.zeros(0), np.zeros((0, 3))

    def load_scene(self, scene, library, fixed: Iterable[int] = ()) -> None:
        """Replace the world's bodies by the scene's objects, at rest at the scene's poses.

        Masses come from the asset records (kg); ``fixed`` lists object indices made static (pinned).
        Wall and ceiling mounts (:func:`spread.scene.welded_objects`) are welded: static, and
        :meth:`unfreeze` leaves them so.
        """
        from spread.scene import welded_objects

        pb, p = self._pb, self.params
        self.clear()
        shapes = [self.body_shape(library, aid) for aid in scene.asset_id]
        self._com = np.stack([s.com for s in shapes]) if shapes else np.zeros((0, 3))
        self._axes = np.stack([s.axes for s in shapes]) if shapes else np.zeros((0, 3, 3))
        self._mass = np.array([float(library[aid].mass) for aid in scene.asset_id])
        unusable = ~np.isfinite(self._mass) | (self._mass <= 0)
        if unusable.any():  # a NaN or infinite mass would leave the world wrong for every later scene too
            first = int(np.argmax(unusable))
            raise ValueError(f"asset '{scene.asset_id[first]}' has mass {self._mass[first]} kg; physics needs a "
                             f"finite positive mass")
        self._inertia = np.stack([s.inertia_per_kg for s in shapes]) * self._mass[:, None] if shapes \
            else np.zeros((0, 3))
        pos, quat = scene_to_body(scene.translation, scene.rotation, self._com, self._axes)
        sleep = pb.ACTIVATION_STATE_ENABLE_SLEEPING if p.allow_sleeping else pb.ACTIVATION_STATE_DISABLE_SLEEPING
        for i, shape in enumerate(shapes):
            body = self._call("createMultiBody", baseMass=float(self._mass[i]),
                              baseCollisionShapeIndex=shape.collision_id,
                              basePosition=pos[i].tolist(), baseOrientation=quat[i].tolist(),
                              useMaximalCoordinates=True)
            # mass goes with the inertia: pybullet zeroes a rigid body's mass when given the inertia alone
            self._call("changeDynamics", body, -1, mass=float(self._mass[i]),
                       localInertiaDiagonal=self._inertia[i].tolist(),
                       lateralFriction=self._object_friction, rollingFriction=p.rolling_friction,
                       spinningFriction=p.spinning_friction, restitution=p.restitution,
                       linearDamping=0.0, angularDamping=0.0, activationState=sleep)
            self._bodies.append(body)
        self._welded = set(np.flatnonzero(welded_objects(scene)).tolist())
        self.freeze(set(int(i) for i in fixed) | self._welded)

    # ---- state -------------------------------------------------------------------------------
    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Current Scene poses: translation (N, 3) bbox centres, rotation (N, 3, 3) world-from-local."""
        n = len(self._bodies)
        pos, quat = np.zeros((n, 3)), np.zeros((n, 4))
        for i, body in enumerate(self._bodies):
            pos[i], quat[i] = self._call("getBasePositionAndOrientation", body)
        return body_to_scene(pos, quat, self._com, self._axes)

    def set_poses(self, translation: np.ndarray, rotation: np.ndarray, zero_velocity: bool = True) -> None:
        """Teleport every object to Scene poses (N, 3) / (N, 3, 3); by default also stop it."""
        pos, quat = scene_to_body(translation, rotation, self._com, self._axes)
        for i, body in enumerate(self._bodies):
            self._call("resetBasePositionAndOrientation", body, pos[i].tolist(), quat[i].tolist())
            if zero_velocity:
                self._call("resetBaseVelocity", body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])

    def velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """(linear (N, 3) m/s of each centre of mass, angular (N, 3) rad/s), world frame."""
        n = len(self._bodies)
        lin, ang = np.zeros((n, 3)), np.zeros((n, 3))
        for i, body in enumerate(self._bodies):
            lin[i], ang[i] = self._call("getBaseVelocity", body)
        return lin, ang

    def set_time_step(self, seconds: float) -> None:
        """Length of one internal step (``step(1)``), seconds."""
        self.time_step = float(seconds)
        self._call("setTimeStep", self.time_step)

    def step(self, n: int = 1) -> None:
        """Advance ``n`` internal steps of ``time_step`` seconds each."""
        pb_step, client = self._pb.stepSimulation, self.client
        for _ in range(int(n)):
            pb_step(physicsClientId=client)

    # ---- pinning -----------------------------------------------------------------------------
    def freeze(self, indices: Iterable[int]) -> None:
        """Make objects static (mass 0: they push, nothing moves them) and stop them."""
        for i in indices:
            i = int(i)
            body = self._bodies[i]
            self._call("changeDynamics", body, -1, mass=0.0)
            self._call("resetBaseVelocity", body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
            self._frozen.add(i)

    def unfreeze(self, indices: Iterable[int] | None = None) -> None:
        """Give frozen objects (all of them by default) their mass and inertia back."""
        for i in list(self._frozen if indices is None else indices):
            i = int(i)
            if i in self._frozen and i not in getattr(self, "_welded", ()):
                self._call("changeDynamics", self._bodies[i], -1, mass=float(self._mass[i]),
                           localInertiaDiagonal=self._inertia[i].tolist())
                self._frozen.discard(i)

    @property
    def frozen(self) -> list[int]:
        return sorted(self._frozen)

    # ---- queries -----------------------------------------------------------------------------
    def contacts(self, distance: float = 0.0) -> ContactSet:
        """Contact points at the current poses with separation ≤ ``distance`` metres (0: touching or
        interpenetrating), between objects and with the floor (index −1). See :class:`ContactSet`.

        Runs Bullet's collision detection first, so it works right after :meth:`load_scene` or
        :meth:`set_poses`; normal forces are those of the last step. ``distance`` may not exceed the
        world's ``contact_breaking_threshold`` (Bullet keeps no farther points). Calling this between steps
        refreshes Bullet's contact cache, which can change the following steps at round-off level.
        """
        if distance > self.params.contact_breaking_threshold:
            raise ValueError(f"contacts(distance={distance}): larger than contact_breaking_threshold "
                             f"{self.params.contact_breaking_threshold} m of this world's PhysicsParams")
        self._call("performCollisionDetection")
        index_of_body = {b: i for i, b in enumerate(self._bodies)}
        index_of_body[self.floor_id] = FLOOR
        points = [pt for pt in self._call("getContactPoints") if pt[8] <= distance]
        return contact_set(points, index_of_body)

    # ---- settling ----------------------------------------------------------------------------
    def settle(self, max_steps: int = 2400, linear_tol: float = 5e-3, angular_tol: float = 5e-2,
               patience: int = 24, fixed: Iterable[int] = ()) -> SettleResult:
        """Simulate until every body is at rest, at most ``max_steps`` internal steps.

        At rest: every centre of mass slower than ``linear_tol`` m/s and every angular speed below
        ``angular_tol`` rad/s for ``patience`` consecutive steps (24 × 1/240 s = 0.1 s by default).
        ``fixed`` objects are frozen for the duration (on top of any frozen before) and unfrozen after.
        """
        pinned = [int(i) for i in fixed if int(i) not in self._frozen]
        self.freeze(pinned)
        calm, steps, settled = 0, 0, False
        try:
            while steps < max_steps:
                self.step(1)
                steps += 1
                lin, ang = self.velocities()
                moving = len(lin) and (np.linalg.norm(lin, axis=1).max() >= linear_tol
                                       or np.linalg.norm(ang, axis=1).max() >= angular_tol)
                calm = 0 if moving else calm + 1
                if calm >= patience:
                    settled = True
                    break
        finally:
            self.unfreeze(pinned)
        t, R = self.poses()
        return SettleResult(t, R, steps, settled)


register_engine(EngineSpec("pybullet", PhysicsParams, PhysicsWorld, "pybullet (Bullet), the reference engine"))
