"""MuJoCo Warp (MJWarp): the runs of a scene stepped together as a batch of worlds, on a GPU or on the CPU.

The same model as :class:`~spread.physics.mujoco_world.MujocoWorld` — the MJCF of
:func:`spread.physics.mjcf.scene_mjcf` with the same :class:`~spread.physics.mujoco_world.MujocoParams`,
compiled by C MuJoCo — copied to the device (``mujoco_warp.put_model``) with one world per run
(``make_data(nworld=runs)``); every run starts from rest at its own initial poses (``reset_data``, then
``qpos``), and all worlds advance together, ``nstep`` calls of ``mujoco_warp.step``. Poses in and out are
the Scene's (y-up, metres, bbox-centre ``t``, world-from-local ``R``). One step is captured as a graph
and replayed (MJWarp's recommended path on CUDA; Warp ≥ 1.19 replays captured launches on the CPU too).

What differs from C MuJoCo (MJWarp's documented differences, mujoco/doc/mjwarp/index.rst):

* float32 arithmetic (C MuJoCo: float64); the solver ``tolerance`` is clamped to at least 1e-6.
* Colliders: MJWarp sends box–box pairs through its general convex pipeline (GJK/EPA, up to 4 contacts)
  unless ``NATIVECCD`` is disabled; it is, on the device model only, so that box–box pairs use MJWarp's
  port of C MuJoCo's own box–box collider (up to 8 contacts), as C MuJoCo does. With GJK/EPA a stack of
  books that topples in 3 of 10 runs in C MuJoCo stood in all of them. Plane–mesh gives up to 4 contacts
  (C: 3); the other pairs use the same kind of collider as C MuJoCo (plane–box primitive, convex meshes
  GJK/EPA with multiccd).
* ``autoreset`` does not exist in MJWarp (it never resets a diverging world), so the MJCF's
  ``autoreset="disable"`` flag is cleared before the copy; the behaviour is the one the MJCF asks for.
  C MuJoCo's ``mjWARN_BADQACC`` has no MJWarp counterpart: a run diverged when its state is non-finite.
* Contacts and constraint rows live in fixed-size buffers (``nconmax`` contacts per world, pooled over the
  worlds; ``njmax`` rows per world, strict). They are sized from the scene (:meth:`MujocoWarpWorld.buffers`),
  and ``Data.overflow`` is read every :data:`OVERFLOW_CHECK_STEPS` steps: a batch that overflowed is
  stopped, discarded and run again with doubled buffers (a logged warning), up to ``overflow_retries``
  times, then :class:`RuntimeError`; an EPA horizon overflow (a convex collision left undefined) raises.
  A world that stopped at the solver's iteration cap (C MuJoCo stops there silently) is logged as a warning.

Warp and MJWarp are imported only when a world is created (the optional extra ``spread[gpu-physics]``).
Kernels are compiled on first use and cached by Warp (``~/.cache/warp``): the first call of a process on a
new machine compiles for tens of seconds on CPU; later processes load them in about a second.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from spread.physics.mujoco_world import MujocoWorld, WeldedPoses
from spread.physics.params import MujocoParams
from spread.physics.engines import EngineSpec, register_engine

log = logging.getLogger("spread.physics.warp")

#: m: geom pairs whose bounding boxes come this close at the start count towards the contact buffer.
CONTACT_REACH = 0.01
#: internal steps between two reads of ``Data.overflow`` (a batch that overflowed stops there and is rerun).
OVERFLOW_CHECK_STEPS = 100


@dataclass(frozen=True)
class MujocoWarpParams(MujocoParams):
    """:class:`~spread.physics.mujoco_world.MujocoParams` (the same model settings; ``threads`` is unused:
    the worlds of a batch run together on the device) plus MJWarp's own settings.

    device: ``"cpu"``, ``"cuda"`` / ``"cuda:K"``, or ``"auto"`` (the first CUDA device if Warp finds one,
        else the CPU).
    nconmax / njmax: contacts per world (pooled over the worlds) / constraint rows per world to allocate
        first; None: sized from the scene (:meth:`MujocoWarpWorld.buffers`).
    overflow_retries: times a batch whose buffers overflowed is run again with doubled buffers before
        :class:`RuntimeError`.
    graph_capture: capture one step's kernel launches as a graph and replay it (CUDA graphs; on the CPU
        Warp replays the recorded launches: same results bit for bit, half the time of launching them from
        Python on this machine).
    """

    device: str = "auto"
    nconmax: int | None = None
    njmax: int | None = None
    overflow_retries: int = 3
    graph_capture: bool = True

    def __post_init__(self) -> None:
        if not (self.device in ("auto", "cpu", "cuda") or str(self.device).startswith("cuda:")):
            raise ValueError(f"MujocoWarpParams.device must be 'auto', 'cpu', 'cuda' or 'cuda:K', got {self.device!r}")
        for name in ("nconmax", "njmax"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"MujocoWarpParams.{name} must be ≥ 1 or None, got {value}")
        if self.overflow_retries < 0:
            raise ValueError(f"MujocoWarpParams.overflow_retries must be ≥ 0, got {self.overflow_retries}")


def _warp():
    """Warp and MJWarp, imported and initialised once (Warp's info log lowered to warnings)."""
    try:
        import warp as wp
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise ImportError("protocol.physics=mujoco_warp needs MuJoCo Warp: pip install 'spread[gpu-physics]' "
                          "(mujoco-warp, warp-lang)") from err
    import mujoco_warp as mjw

    if not getattr(_warp, "done", False):
        wp.config.log_level = wp.LOG_WARNING  # no "Module ... load on device" line per kernel
        wp.init()
        _warp.done = True
    return wp, mjw


def resolve_device(name: str) -> str:
    """Warp device name for a :attr:`MujocoWarpParams.device` setting (``auto``: CUDA if available)."""
    wp, _ = _warp()
    if name == "auto":
        return "cuda:0" if wp.is_cuda_available() else "cpu"
    if name.startswith("cuda") and not wp.is_cuda_available():
        raise RuntimeError(f"MujocoWarpParams.device={name!r} but Warp finds no CUDA device; use 'cpu' or 'auto'")
    return name


class MujocoWarpWorld:
    """One scene's MJWarp model at a time, and a batch of worlds (one per run) for :meth:`simulate`.

    The interface :func:`~spread.physics.runs.simulate_runs` uses: ``params``, ``time_step``,
    ``set_time_step``, ``load_scene``, ``simulate``; also ``close`` / context manager, as the other worlds.
    Not thread-safe.
    """

    engine = "mujoco_warp"

    def __init__(self, params: MujocoWarpParams | None = None):
        import mujoco

        from spread.physics.mujoco_world import _route_warnings

        _route_warnings(mujoco)
        self._mj = mujoco
        self._wp, self._mjw = _warp()
        self.params = params or MujocoWarpParams()
        self.device = resolve_device(self.params.device)
        self.time_step = self.params.time_step
        self.mjm = None  # the C MuJoCo model of the loaded scene
        self.model = None  # its MJWarp copy on the device
        self.data = None
        self._key = None
        self._data_key = None
        self._graph = None
        self._buffers: tuple[int, int] | None = None
        self.models_compiled = 0
        self.last_overflow: np.ndarray | None = None  # per-world Data.overflow bitmask of the last batch kept

    # ---- scenes ------------------------------------------------------------------------------
    @property
    def num_objects(self) -> int:
        return 0 if self.mjm is None else int(self.mjm.nbody) - 1

    def load_scene(self, scene, library, fixed=()) -> None:
        """Compile ``scene``'s model (reused when its bodies are those of the scene already loaded) and copy
        it to the device. ``fixed`` is not supported (no pinned bodies, as in MujocoWorld)."""
        if len(tuple(fixed)):
            raise NotImplementedError("MujocoWarpWorld cannot pin objects; use the pybullet PhysicsWorld to settle")
        key = MujocoWorld._scene_key(scene, library)
        if key == self._key:
            return
        from spread.physics.mjcf import scene_mjcf

        mj = self._mj
        mjm = mj.MjModel.from_xml_string(scene_mjcf(scene, library, self.params))
        mjm.opt.disableflags &= ~int(mj.mjtDisableBit.mjDSBL_AUTORESET)  # MJWarp has no autoreset (docstring)
        mjm.opt.timestep = self.time_step
        with self._wp.ScopedDevice(self.device):
            self.model = self._mjw.put_model(mjm)
        self.model.opt.warn_overflow = 0  # read Data.overflow instead of printing from kernels
        self.model.opt.disableflags |= self._mjw.DisableBit.NATIVECCD  # box–box: C MuJoCo's collider (docstring)
        self.mjm = mjm
        self.welded = WeldedPoses.of(scene)
        self._buffers = self.buffers(scene)
        self.data, self._data_key, self._graph = None, None, None
        self._key = key
        self.models_compiled += 1

    def buffers(self, scene) -> tuple[int, int]:
        """(nconmax, njmax) to allocate first for ``scene`` (the loaded model): the params' values, else an
        estimate from the scene's poses. Every pair of collision geoms of different bodies (or a geom and the
        floor) whose world bounding boxes, grown by :data:`CONTACT_REACH`, overlap may touch, with at most
        MJWarp's contacts per pair of that kind (8 box–box, 4 else); plus 8 per object and 16 for contacts
        that falling objects make elsewhere. Rows: that many contacts × 2 (condim − 1) (pyramidal cone) or
        condim (elliptic). A scene whose contacts outgrow this is caught by ``Data.overflow`` and rerun."""
        p = self.params
        nconmax = p.nconmax or int(self._pair_contacts(scene)) + 8 * self.num_objects + 16
        rows = 2 * (p.condim - 1) if p.cone == "pyramidal" else p.condim
        return int(nconmax), int(p.njmax or rows * nconmax)

    def _pair_contacts(self, scene) -> int:
        """Upper bound on the contacts of the geom pairs close at ``scene``'s poses (:meth:`buffers`)."""
        mj, m = self._mj, self.mjm
        d = mj.MjData(m)
        d.qpos[:] = self.welded.qpos(scene.translation, scene.rotation)
        mj.mj_kinematics(m, d)
        dyn = np.flatnonzero((m.geom_bodyid > 0) & ((m.geom_contype | m.geom_conaffinity) > 0))
        aabb = m.geom_aabb.reshape(-1, 2, 3)[dyn]  # local (centre, half extents)
        rot = d.geom_xmat[dyn].reshape(-1, 3, 3)
        centre = d.geom_xpos[dyn] + np.einsum("gij,gj->gi", rot, aabb[:, 0])
        half = np.einsum("gij,gj->gi", np.abs(rot), aabb[:, 1]) + CONTACT_REACH / 2
        box = m.geom_type[dyn] == mj.mjtGeom.mjGEOM_BOX
        body = m.geom_bodyid[dyn]
        near = (np.abs(centre[:, None] - centre[None]) <= half[:, None] + half[None]).all(-1)
        near &= (body[:, None] != body[None]) & np.triu(np.ones((len(dyn),) * 2, bool), 1)
        per_pair = np.where(box[:, None] & box[None], 8, 4)
        on_floor = centre[:, 1] - half[:, 1] <= 0.0  # the floor plane y = 0: 4 contacts with any geom
        return int((per_pair * near).sum() + 4 * on_floor.sum())

    def set_time_step(self, seconds: float) -> None:
        """Length of one internal step (one ``mujoco_warp.step``), seconds."""
        self.time_step = float(seconds)

    # ---- runs ----------------------------------------------------------------------------------
    def simulate(self, scene, library, translation: np.ndarray, rotation: np.ndarray, nstep: int) -> tuple:
        """Runs of ``scene`` from initial poses translation (runs, N, 3) and rotation (N, 3, 3) or
        (runs, N, 3, 3), each ``nstep`` internal steps from rest, all runs one batch of worlds. Returns final
        (translation (runs, N, 3), rotation (runs, N, 3, 3)), float64 from MJWarp's float32 state."""
        translation = np.asarray(translation, np.float64)
        runs, n = translation.shape[:2]
        rotation = np.broadcast_to(np.asarray(rotation, np.float64), (runs, n, 3, 3))
        self.load_scene(scene, library)
        if n != self.num_objects:
            raise ValueError(f"MujocoWarpWorld: {n} poses for a scene of {self.num_objects} objects")
        if runs == 0:
            return np.zeros((0, n, 3)), np.zeros((0, n, 3, 3))
        qpos = np.stack([self.welded.qpos(translation[r], rotation[r]) for r in range(runs)])
        mjw = self._mjw
        buffer_bits = int(mjw.OverflowType.NEFC | mjw.OverflowType.NJMAX_NNZ | mjw.OverflowType.BROADPHASE
                          | mjw.OverflowType.NARROWPHASE | mjw.OverflowType.CCD | mjw.OverflowType.NVMAX)
        nconmax, njmax = self._buffers
        for attempt in range(self.params.overflow_retries + 1):
            final, qvel, overflow = self._batch(qpos, int(nstep), nconmax, njmax, buffer_bits)
            if not (overflow & buffer_bits).any():
                break
            bits = mjw.OverflowType(int(np.bitwise_or.reduce(overflow & buffer_bits)))
            if attempt == self.params.overflow_retries:
                raise RuntimeError(f"MuJoCo Warp: scene '{scene.scene_id}' overflowed its buffers ({bits!r}) with "
                                   f"nconmax={nconmax}, njmax={njmax} after {attempt} doublings; set "
                                   "MujocoWarpParams.nconmax / njmax higher")
            log.warning("MuJoCo Warp: scene '%s' overflowed %r with nconmax=%d, njmax=%d; running the batch again "
                        "with both doubled", scene.scene_id, bits, nconmax, njmax)
            nconmax, njmax = 2 * nconmax, 2 * njmax
        self._buffers = (nconmax, njmax)  # the next batch of this scene starts from buffers that sufficed
        bits = int(mjw.OverflowType.EPA_HORIZON)
        if (overflow & bits).any():
            raise RuntimeError(f"MuJoCo Warp: scene '{scene.scene_id}': EPA horizon overflow in convex collision "
                               f"in {int(((overflow & bits) != 0).sum())} of {runs} worlds (contacts undefined); "
                               "raise ccd_iterations")
        capped = ((overflow & int(mjw.OverflowType.ITERATIONS | mjw.OverflowType.LS_ITERATIONS)) != 0).sum()
        if capped:
            log.warning("MuJoCo Warp: scene '%s': the solver reached its iteration cap in %d of %d worlds",
                        scene.scene_id, int(capped), runs)
        self.last_overflow = overflow
        if not (np.isfinite(final).all() and np.isfinite(qvel).all()):
            raise FloatingPointError(f"MuJoCo Warp simulation of scene '{scene.scene_id}' diverged (non-finite "
                                     f"state); time step {self.time_step} s is too long for these contacts")
        return self.welded.poses(final)

    def _batch(self, qpos: np.ndarray, nstep: int, nconmax: int, njmax: int, stop_bits: int):
        """Step one world per row of ``qpos`` (runs, nq) from rest for ``nstep`` steps, reading
        ``Data.overflow`` every :data:`OVERFLOW_CHECK_STEPS` steps and stopping early once a bit of
        ``stop_bits`` is set. Returns final qpos (runs, nq) float64, qvel (runs, nv), Data.overflow (runs,)."""
        wp, mjw = self._wp, self._mjw
        with wp.ScopedDevice(self.device):
            key = (len(qpos), nconmax, njmax)
            if key != self._data_key:
                self.data = mjw.make_data(self.mjm, nworld=len(qpos), nconmax=nconmax, njmax=njmax)
                self._data_key, self._graph = key, None
            m, d = self.model, self.data
            m.opt.timestep.fill_(self.time_step)
            mjw.reset_data(m, d)
            d.qpos.assign(qpos.astype(np.float32))
            step = lambda: mjw.step(m, d)  # noqa: E731
            if self.params.graph_capture:
                if self._graph is None:  # a captured step reads the arrays in place: the state set above is used
                    with wp.ScopedCapture() as capture:
                        mjw.step(m, d)
                    self._graph = capture.graph
                step = lambda: wp.capture_launch(self._graph)  # noqa: E731
            done, overflow = 0, d.overflow.numpy().astype(np.int64)
            while done < nstep:
                for _ in range(min(OVERFLOW_CHECK_STEPS, nstep - done)):
                    step()
                done += OVERFLOW_CHECK_STEPS
                overflow = d.overflow.numpy().astype(np.int64)  # waits for the device
                if (overflow & stop_bits).any():
                    break
            return d.qpos.numpy().astype(np.float64), d.qvel.numpy(), overflow

    def close(self) -> None:
        """Release the model, data and captured graph."""
        self.mjm = self.model = self.data = self._graph = None
        self._key = self._data_key = None

    def __enter__(self) -> "MujocoWarpWorld":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


register_engine(EngineSpec("mujoco_warp", MujocoWarpParams, MujocoWarpWorld,
                           "MuJoCo Warp: a scene's runs as one batch of worlds (GPU, or CPU); extra gpu-physics"))
