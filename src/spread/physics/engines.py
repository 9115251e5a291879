"""The physics-engine registry: each Stability engine defined once, in its own module (``protocol.physics=<name>``).

An :class:`EngineSpec` is an engine's name, its parameters' dataclass (every field in SI units; the world's type
is picked by the parameters' type, :func:`spread.physics.get_world`), its world class (or ``"module:Class"``;
pybullet, MuJoCo and MuJoCo Warp themselves are imported when a world is created) and ``options``: the
parameters it takes from the evaluation protocol besides the time step (MuJoCo's sleeping islands). Each
engine module registers itself at its end (:func:`register_engine`): ``pybullet`` (the reference,
:mod:`spread.physics.world`), ``mujoco`` (:mod:`spread.physics.mujoco_world`), ``mujoco_warp``
(:mod:`spread.physics.warp_world`); the registry imports every module of :mod:`spread.physics` when first read,
so a new engine is one module. Another package adds an engine through the entry-point group ``spread.physics``
naming an :class:`EngineSpec`; its world implements what :func:`spread.physics.simulate_runs` uses (``params``,
``time_step``, ``set_time_step``, ``load_scene``, ``set_poses``, ``step``, ``poses``, ``velocities``, ``close``;
optionally ``simulate``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from spread.registry import Registry, RegistryError, resolve


@dataclass(frozen=True)
class EngineSpec:
    """One engine (module docstring); ``options(protocol) → dict`` of its parameters' fields set by the protocol."""

    name: str
    params: type
    world: object  # the class or "module:Class"
    description: str = ""
    options: Callable | None = None

    def world_class(self):
        return resolve(self.world)

    def params_for(self, protocol, time_step: float):
        """The engine's parameters for an evaluation ``protocol`` at the internal step ``time_step`` (seconds)."""
        return self.params(time_step=time_step, **(self.options(protocol) if self.options is not None else {}))


def _adapt(name: str, obj) -> EngineSpec:
    if isinstance(obj, EngineSpec):
        return obj if obj.name == name else EngineSpec(name, obj.params, obj.world, obj.description, obj.options)
    raise RegistryError(f"physics entry point '{name}': expected an EngineSpec, got {obj!r}")


ENGINES: Registry[EngineSpec] = Registry("physics engine", "spread.physics", packages=("spread.physics",),
                                         adapt=_adapt)


def register_engine(spec: EngineSpec) -> EngineSpec:
    return ENGINES.register(spec.name, spec, origin=str(spec.world))


def engine_of(params) -> EngineSpec:
    """The engine whose parameters' type is ``type(params)`` (the most derived match)."""
    matches = [s for _, s in ENGINES.items() if type(params) is s.params]
    if not matches:
        raise RegistryError(f"no registered physics engine takes {type(params).__name__} (engines: {ENGINES.names()})")
    return matches[0]
