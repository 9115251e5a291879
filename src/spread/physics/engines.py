"""The physics-engine registry: each Stability engine defined once (``protocol.physics=<name>``).

An :class:`EngineSpec` is an engine's name, its parameters' dataclass (every field in SI units; the world's type
is picked by the parameters' type, :func:`spread.physics.get_world`) and its world class (``"module:Class"``,
imported when a world is created: pybullet, MuJoCo and MuJoCo Warp are optional heavy imports). Built-ins:
``pybullet`` (the reference), ``mujoco``, ``mujoco_warp``. Another package adds an engine through the
entry-point group ``spread.physics`` naming an :class:`EngineSpec`; its world implements what
:func:`spread.physics.simulate_runs` uses (``params``, ``time_step``, ``set_time_step``, ``load_scene``,
``set_poses``, ``step``, ``poses``, ``velocities``, ``close``; optionally ``simulate``).
"""

from __future__ import annotations

from dataclasses import dataclass

from spread.physics.params import MujocoParams, PhysicsParams
from spread.physics.warp_world import MujocoWarpParams
from spread.registry import Registry, RegistryError, resolve


@dataclass(frozen=True)
class EngineSpec:
    name: str
    params: type
    world: object  # "module:Class" or the class
    description: str = ""

    def world_class(self):
        return resolve(self.world)


def _adapt(name: str, obj) -> EngineSpec:
    if isinstance(obj, EngineSpec):
        return obj if obj.name == name else EngineSpec(name, obj.params, obj.world, obj.description)
    raise RegistryError(f"physics entry point '{name}': expected an EngineSpec, got {obj!r}")


ENGINES: Registry[EngineSpec] = Registry("physics engine", "spread.physics", adapt=_adapt)


def register_engine(spec: EngineSpec) -> EngineSpec:
    return ENGINES.register(spec.name, spec, origin=str(spec.world))


def engine_of(params) -> EngineSpec:
    """The engine whose parameters' type is ``type(params)`` (the most derived match)."""
    matches = [s for _, s in ENGINES.items() if type(params) is s.params]
    if not matches:
        raise RegistryError(f"no registered physics engine takes {type(params).__name__} (engines: {ENGINES.names()})")
    return matches[0]


register_engine(EngineSpec("pybullet", PhysicsParams, "spread.physics.world:PhysicsWorld",
                           "pybullet (Bullet), the reference engine"))
register_engine(EngineSpec("mujoco", MujocoParams, "spread.physics.mujoco_world:MujocoWorld",
                           "C MuJoCo, the same bodies compiled to MJCF"))
register_engine(EngineSpec("mujoco_warp", MujocoWarpParams, "spread.physics.warp_world:MujocoWarpWorld",
                           "MuJoCo Warp: a scene's runs as one batch of worlds (GPU, or CPU); extra gpu-physics"))
