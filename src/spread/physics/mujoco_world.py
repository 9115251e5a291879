"""A MuJoCo world built from Scenes: the Stability protocol's second engine, beside pybullet.

Same bodies as :class:`~spread.physics.world.PhysicsWorld` (the asset's exact convex parts, its mass,
the inertia of its watertight mesh about its centre of mass; :mod:`spread.physics.mjcf`), same frame
(y-up, metres, floor the plane y = 0), same poses in and out (Scene bbox-centre ``t``, world-from-local
``R``). A scene is compiled into one ``MjModel`` (:meth:`MujocoWorld.load_scene`); the model of the
last scene is kept, so the runs of one scene reuse it.

Runs (:meth:`MujocoWorld.simulate`): every run starts from ``mj_resetData`` (no warm start or contact
carried over, like pybullet's fresh bodies) at its own initial poses, zero velocities. With
``threads`` > 1 the runs are stepped together by ``mujoco.rollout`` on that many threads, one
``MjData`` per thread (same results as one thread, bit for bit: each run is independent).

MuJoCo is imported only when a world is created.
"""

from __future__ import annotations

import numpy as np

from spread.physics.params import MujocoParams  # noqa: F401  (defined beside the other engines' parameters)
from spread.physics.engines import EngineSpec, register_engine


def _route_warnings(mujoco) -> None:
    """Send MuJoCo's warnings to Python's ``logging`` (logger ``spread.physics.mujoco``) instead of its default,
    which appends to ``MUJOCO_LOG.TXT`` in the working directory. Once per process."""
    if getattr(_route_warnings, "done", False):
        return
    import logging

    log = logging.getLogger("spread.physics.mujoco")
    mujoco.set_mju_user_warning(lambda text: log.warning("MuJoCo: %s", text))
    _route_warnings.done = True


class WeldedPoses:
    """Which objects of a scene are welded (wall and ceiling mounts: bodies without a joint in
    :func:`~spread.physics.mjcf.scene_mjcf`) and their scene poses; maps Scene poses of all N objects to the
    free bodies' ``qpos`` (7 per free body: position, wxyz quaternion) and back (welded ones where they are)."""

    def __init__(self, welded: np.ndarray, translation: np.ndarray, rotation: np.ndarray):
        self.welded = np.asarray(welded, bool)
        self.translation = np.asarray(translation, np.float64).reshape(-1, 3)[self.welded]
        self.rotation = np.asarray(rotation, np.float64).reshape(-1, 3, 3)[self.welded]

    @classmethod
    def of(cls, scene) -> "WeldedPoses":
        from spread.scene import welded_objects

        return cls(welded_objects(scene), scene.translation, scene.rotation)

    def key(self) -> tuple:
        """What a compiled model depends on: which objects are welded, and where (their poses are in it)."""
        return (tuple(np.flatnonzero(self.welded).tolist()), self.translation.round(9).tobytes(),
                self.rotation.round(9).tobytes())

    def qpos(self, translation: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        from spread.physics.mjcf import matrix_to_wxyz

        free = ~self.welded
        t = np.asarray(translation, np.float64).reshape(-1, 3)[free]
        q = matrix_to_wxyz(np.asarray(rotation, np.float64).reshape(-1, 3, 3)[free])
        return np.concatenate([t, q], axis=1).ravel()

    def poses(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scene poses (..., N, 3) / (..., N, 3, 3) of ``qpos`` (..., 7 · free)."""
        from spread.physics.frames import quat_to_matrix

        qpos = np.asarray(qpos, np.float64)
        q = qpos.reshape(qpos.shape[:-1] + (-1, 7))
        xyzw = np.concatenate([q[..., 4:7], q[..., 3:4]], axis=-1)
        lead = q.shape[:-2]
        n = len(self.welded)
        t = np.zeros(lead + (n, 3))
        R = np.zeros(lead + (n, 3, 3))
        t[..., ~self.welded, :] = q[..., :3]
        R[..., ~self.welded, :, :] = quat_to_matrix(xyzw.reshape(-1, 4)).reshape(q.shape[:-1] + (3, 3))
        t[..., self.welded, :] = self.translation
        R[..., self.welded, :, :] = self.rotation
        return t, R


class MujocoWorld:
    """MuJoCo model + data of one scene at a time; the floor plane y = 0 and one free body per object.

    The subset of :class:`~spread.physics.world.PhysicsWorld`'s interface that the Stability protocol
    uses (``params``, ``time_step``, ``set_time_step``, ``load_scene``, ``set_poses``, ``step``,
    ``poses``, ``velocities``), plus :meth:`simulate` (many runs of one scene at once). Not thread-safe.
    """

    engine = "mujoco"

    def __init__(self, params: MujocoParams | None = None):
        import mujoco

        _route_warnings(mujoco)
        self._mj = mujoco
        self.params = params or MujocoParams()
        self.time_step = self.params.time_step
        self.model = None
        self.data = None
        self._key = None
        self._datas: list = []
        self._pool = None
        self.models_compiled = 0
        self.steps_simulated = 0  # internal steps actually taken by simulate (fewer than asked when runs sleep)

    # ---- scenes ------------------------------------------------------------------------------
    @property
    def num_objects(self) -> int:
        return 0 if self.model is None else int(self.model.nbody) - 1

    def load_scene(self, scene, library, fixed=()) -> None:
        """Compile ``scene`` (reused when it is the scene already loaded) and put its objects at rest at the
        scene's poses. ``fixed`` is not supported (MuJoCo bodies cannot be pinned and released)."""
        if len(tuple(fixed)):
            raise NotImplementedError("MujocoWorld cannot pin objects; use the pybullet PhysicsWorld to settle")
        key = self._scene_key(scene, library)
        if key != self._key:
            from spread.physics.mjcf import scene_mjcf
            from spread.scene import welded_objects

            self.model = self._mj.MjModel.from_xml_string(scene_mjcf(scene, library, self.params))
            self.model.opt.timestep = self.time_step
            self.data = self._mj.MjData(self.model)
            self._datas = []
            self._key = key
            self.models_compiled += 1
            self.welded = WeldedPoses.of(scene)
        self.set_poses(scene.translation, scene.rotation)

    @staticmethod
    def _scene_key(scene, library) -> tuple:
        """Identifies the bodies (not the poses) of a scene: the model can be reused when this is equal."""
        ids = tuple(str(a) for a in scene.asset_id)
        return ids, tuple(library[a].content_hash for a in ids), tuple(float(library[a].mass) for a in ids), \
            id(library), WeldedPoses.of(scene).key()

    def _qpos(self, translation: np.ndarray, rotation: np.ndarray) -> np.ndarray:
        return self.welded.qpos(translation, rotation)

    def _check(self, n: int) -> None:
        if self.model is None:
            raise RuntimeError("MujocoWorld: no scene loaded (call load_scene first)")
        if n != self.num_objects:
            raise ValueError(f"MujocoWorld: {n} poses for a scene of {self.num_objects} objects")

    # ---- state -------------------------------------------------------------------------------
    def set_poses(self, translation: np.ndarray, rotation: np.ndarray, zero_velocity: bool = True) -> None:
        """Teleport every object to Scene poses (N, 3) / (N, 3, 3); a fresh start: time, velocities, warm
        start and contacts reset (``zero_velocity`` must be True: MuJoCo keeps no velocity across a reset)."""
        if not zero_velocity:
            raise NotImplementedError("MujocoWorld.set_poses always starts from rest")
        self._check(len(np.asarray(translation).reshape(-1, 3)))
        self._mj.mj_resetData(self.model, self.data)
        self.data.qpos[:] = self._qpos(translation, rotation)
        self._mj.mj_forward(self.model, self.data)

    def poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Current Scene poses: translation (N, 3) bbox centres, rotation (N, 3, 3) world-from-local."""
        return self._poses_of(np.asarray(self.data.qpos))

    def _poses_of(self, qpos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.welded.poses(qpos)

    def velocities(self) -> tuple[np.ndarray, np.ndarray]:
        """(linear (N, 3) m/s of each centre of mass, angular (N, 3) rad/s), world frame."""
        n = self.num_objects
        lin, ang = np.zeros((n, 3)), np.zeros((n, 3))
        v = np.zeros(6)
        for i in range(n):  # a body's object frame is its inertial frame: the velocity at the centre of mass
            self._mj.mj_objectVelocity(self.model, self.data, self._mj.mjtObj.mjOBJ_BODY, i + 1, v, 0)
            ang[i], lin[i] = v[:3], v[3:]
        return lin, ang

    def set_time_step(self, seconds: float) -> None:
        """Length of one internal step (``step(1)``), seconds."""
        self.time_step = float(seconds)
        if self.model is not None:
            self.model.opt.timestep = self.time_step

    def step(self, n: int = 1) -> None:
        """Advance ``n`` internal steps of ``time_step`` seconds each."""
        if n > 0:
            self._mj.mj_step(self.model, self.data, nstep=int(n))

    # ---- runs ----------------------------------------------------------------------------------
    def simulate(self, scene, library, translation: np.ndarray, rotation: np.ndarray, nstep: int) -> tuple:
        """Runs of ``scene`` from initial poses translation (runs, N, 3) and rotation (N, 3, 3) or
        (runs, N, 3, 3), each ``nstep`` internal steps from rest. Returns final (translation (runs, N, 3),
        rotation (runs, N, 3, 3)). ``params.threads`` > 1 steps the runs together (module docstring)."""
        translation = np.asarray(translation, np.float64)
        runs, n = translation.shape[:2]
        rotation = np.broadcast_to(np.asarray(rotation, np.float64), (runs, n, 3, 3))
        self.load_scene(scene, library)
        if runs == 0:
            return np.zeros((0, n, 3)), np.zeros((0, n, 3, 3))
        qpos = np.stack([self._qpos(translation[r], rotation[r]) for r in range(runs)])
        unstable = self._mj.mjtWarning.mjWARN_BADQACC
        diverged = False
        if self.params.threads <= 1 or runs == 1 or self.params.sleep:
            final = np.zeros_like(qpos)
            for r in range(runs):
                self._mj.mj_resetData(self.model, self.data)
                self.data.qpos[:] = qpos[r]
                self._run(int(nstep))
                final[r] = self.data.qpos
                diverged |= self.data.warning[unstable].number > 0
        else:
            final = self._rollout(qpos, int(nstep))
            self.steps_simulated += len(qpos) * int(nstep)
            diverged = any(d.warning[unstable].number > 0 for d in self._datas)
        if diverged or not np.isfinite(final).all():
            raise FloatingPointError(f"MuJoCo simulation of scene '{scene.scene_id}' diverged (huge or non-finite "
                                     f"accelerations); time step {self.time_step} s is too long for these contacts")
        return self._poses_of(final)

    #: Internal steps between two checks of whether every body sleeps (MuJoCo's own wait before sleeping).
    SLEEP_CHECK = 10

    def _run(self, nstep: int) -> None:
        """Step ``self.data`` ``nstep`` internal steps; with sleep on, stop early once every body sleeps (a world
        whose islands all sleep stays exactly as it is: sleeping bodies are frozen and nothing awake can wake
        them)."""
        if not self.params.sleep:
            self._mj.mj_step(self.model, self.data, nstep=nstep)
            self.steps_simulated += nstep
            return
        done = 0
        while done < nstep:
            k = min(self.SLEEP_CHECK, nstep - done)
            self._mj.mj_step(self.model, self.data, nstep=k)
            done += k
            if self.data.ntree_awake == 0:
                break
        self.steps_simulated += done

    def _rollout(self, qpos: np.ndarray, nstep: int) -> np.ndarray:
        """Final qpos (runs, nq) of runs started from rest at ``qpos`` (runs, nq), stepped on threads."""
        from mujoco import rollout

        mj, m = self._mj, self.model
        threads = min(int(self.params.threads), len(qpos))
        while len(self._datas) < threads:
            self._datas.append(mj.MjData(m))
        for d in self._datas:
            mj.mj_resetData(m, d)  # clears the warning counters read after the rollout
        if self._pool is None:
            self._pool = rollout.Rollout(nthread=int(self.params.threads))
        spec = mj.mjtState.mjSTATE_FULLPHYSICS
        scratch = mj.MjData(m)
        initial = np.zeros((len(qpos), mj.mj_stateSize(m, spec)))
        for r in range(len(qpos)):
            mj.mj_resetData(m, scratch)
            scratch.qpos[:] = qpos[r]
            mj.mj_getState(m, scratch, initial[r], spec)
        state, _ = self._pool.rollout(m, self._datas[:threads], initial, nstep=nstep)
        last = np.ascontiguousarray(state[:, -1])
        final = np.zeros_like(qpos)
        for r in range(len(qpos)):
            mj.mj_setState(m, scratch, last[r], spec)
            final[r] = scratch.qpos
        return final

    def close(self) -> None:
        """Release the model, data and thread pool."""
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        self.model = self.data = None
        self._datas = []
        self._key = None

    def __enter__(self) -> "MujocoWorld":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


register_engine(EngineSpec("mujoco", MujocoParams, MujocoWorld, "C MuJoCo, the same bodies compiled to MJCF",
                           options=lambda protocol: {"sleep": bool(protocol.physics_sleep)}))
