"""One physics world per worker process (Ray task, multiprocessing pool): created on first use.

The engine follows the params' type (the engine registry, :mod:`spread.physics.engines`; plugins too):
:class:`~spread.physics.PhysicsParams` (or none) gives a pybullet
:class:`~spread.physics.world.PhysicsWorld`, :class:`~spread.physics.MujocoParams` a
:class:`~spread.physics.mujoco_world.MujocoWorld`, :class:`~spread.physics.MujocoWarpParams` (a subclass) a
:class:`~spread.physics.warp_world.MujocoWarpWorld` (batched runs, GPU or CPU).

The world lives in a thread-local slot tagged with the process id, so a forked child never reuses its
parent's client and two threads never share one.
"""

from __future__ import annotations

import os
import threading

from spread.physics.params import MujocoParams, PhysicsParams
from spread.physics.warp_world import MujocoWarpParams

_local = threading.local()


def get_world(params: PhysicsParams | MujocoParams | MujocoWarpParams | None = None):
    """This process's (and thread's) physics world, created on first call: pybullet for
    :class:`PhysicsParams` (the default), MuJoCo for :class:`MujocoParams`, MuJoCo Warp for
    :class:`MujocoWarpParams`.

    With ``params`` different from the current world's, the world is closed and rebuilt with them.
    """
    world = getattr(_local, "world", None)
    if world is not None and getattr(_local, "pid", None) != os.getpid():
        world = None  # inherited through fork: that client belongs to the parent
    if world is not None and params is not None and params != world.params:
        world.close()
        world = None
    if world is None:
        from spread.physics.engines import engine_of

        world = engine_of(params if params is not None else PhysicsParams()).world_class()(params)
        _local.world, _local.pid = world, os.getpid()
    return world
