"""The sampler registry: the diffusers schedulers a :class:`~spread.model.sampler.Sampler` runs, by name.

A :class:`SchedulerSpec` is a name (``sampler.kind``), a ``build(config)`` that makes a fresh diffusers scheduler
from the config of the model's training schedule (they are stateful: one per call), and the default number of
steps. Built-ins: ``ddpm`` (ancestral, all 1000 steps by default), ``ddim`` and ``dpmsolver++`` (50 steps),
each with "trailing" timestep spacing (Lin et al. 2024) and DPM-Solver++ clipping λ(t) at −5.1 as diffusers
recommends for the cosine schedule.

Another scheduler is chosen without editing this file: an entry point in the group ``spread.samplers`` naming a
:class:`SchedulerSpec` or a diffusers scheduler class (``sampler.kind=<name>``), or a ``"module:Class"`` target of
any diffusers scheduler class (``sampler.kind=diffusers:EulerDiscreteScheduler``), built with
``Class.from_config(config, timestep_spacing="trailing")``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from spread.registry import Registry, RegistryError, resolve


@dataclass(frozen=True)
class SchedulerSpec:
    """One sampler kind: ``build(training_schedule_config) → diffusers scheduler``; ``steps``: the default count."""

    name: str
    build: Callable
    steps: int = 50
    description: str = ""


def _from_class(name: str, cls, steps: int = 50) -> SchedulerSpec:
    return SchedulerSpec(name, lambda config: cls.from_config(config, timestep_spacing="trailing"), steps,
                         (cls.__doc__ or "").strip().split("\n")[0])


def _adapt(name: str, obj) -> SchedulerSpec:
    if isinstance(obj, SchedulerSpec):
        return obj if obj.name == name else SchedulerSpec(name, obj.build, obj.steps, obj.description)
    if isinstance(obj, type) and hasattr(obj, "from_config"):
        return _from_class(name, obj)
    raise RegistryError(f"sampler entry point '{name}': expected a SchedulerSpec or a diffusers scheduler class, "
                        f"got {obj!r}")


SCHEDULERS: Registry[SchedulerSpec] = Registry("sampler", "spread.samplers", adapt=_adapt)


def register_scheduler(spec: SchedulerSpec) -> SchedulerSpec:
    return SCHEDULERS.register(spec.name, spec, origin=getattr(spec.build, "__module__", ""))


def scheduler_spec(kind: str) -> SchedulerSpec:
    """The spec of ``kind``: a registered name, or a ``"module:Class"`` diffusers scheduler (module docstring);
    anything else is an error naming the registered ones."""
    if ":" in kind:
        try:
            return _from_class(kind, resolve(kind))
        except (ImportError, AttributeError) as exc:
            raise RegistryError(f"sampler kind '{kind}': {type(exc).__name__}: {exc}") from exc
    return SCHEDULERS.get(kind)


def _ddpm(config):
    from diffusers import DDPMScheduler

    return DDPMScheduler.from_config(config, clip_sample=False, timestep_spacing="trailing")


def _ddim(config):
    from diffusers import DDIMScheduler

    return DDIMScheduler.from_config(config, clip_sample=False, timestep_spacing="trailing")


def _dpmsolver(config):
    from diffusers import DPMSolverMultistepScheduler

    return DPMSolverMultistepScheduler.from_config(config, algorithm_type="dpmsolver++", timestep_spacing="trailing",
                                                   lambda_min_clipped=-5.1)


register_scheduler(SchedulerSpec("ddpm", _ddpm, 1000, "ancestral DDPM (fewer than 1000 steps: a strided schedule)"))
register_scheduler(SchedulerSpec("ddim", _ddim, 50, "DDIM, deterministic at eta 0"))
register_scheduler(SchedulerSpec("dpmsolver++", _dpmsolver, 50, "DPM-Solver++ (multistep, second order)"))
