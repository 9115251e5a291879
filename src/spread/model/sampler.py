"""The sampler's settings, without torch: :class:`Sampler` (kind, steps, eta, clip_x0) and the default training
schedule (:data:`TRAIN_SCHEDULER_CONFIG`).

A command reads, checks and fingerprints its sampler before anything heavy loads, so a refused setting is
refused in the time it takes to compose the config: this module imports neither torch nor diffusers
(``tests/test_layout.py`` pins that). Building a scheduler loads diffusers; the reverse process a sampler runs is
:func:`spread.model.diffusion.reverse_process`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Mapping

if TYPE_CHECKING:  # diffusers loads with the first scheduler
    from diffusers import DDPMScheduler

TRAIN_SCHEDULER_CONFIG: dict = {
    "num_train_timesteps": 1000,
    "beta_schedule": "squaredcos_cap_v2",
    "prediction_type": "epsilon",
}
#: The built-in sampler kinds (every registered one: :data:`spread.model.schedulers.SCHEDULERS`).
SAMPLER_KINDS = ("ddpm", "ddim", "dpmsolver++")


#: The beta schedules diffusers' DDPMScheduler makes by name.
BETA_SCHEDULES = ("linear", "scaled_linear", "squaredcos_cap_v2", "laplace", "sigmoid")
#: The most training timesteps a schedule may have: diffusers makes the cosine schedule in a Python loop over them
#: (a checkpoint saying ``diffusion_steps: 1e12`` held the command in it, its memory growing, with no end).
MAX_DIFFUSION_STEPS = 100_000


def check_schedule(beta_schedule, steps) -> None:
    """``ValueError`` naming the hyperparameter when a training schedule cannot be made: an unknown
    ``beta_schedule`` (diffusers raised ``NotImplementedError: bogus is not implemented``), or ``diffusion_steps``
    not a whole number in [1, :data:`MAX_DIFFUSION_STEPS`]."""
    if beta_schedule not in BETA_SCHEDULES:
        raise ValueError(f"beta_schedule={beta_schedule!r}: not a beta schedule (known: {', '.join(BETA_SCHEDULES)})")
    whole = isinstance(steps, int) and not isinstance(steps, bool) or isinstance(steps, float) and steps.is_integer()
    if not whole or not 1 <= steps <= MAX_DIFFUSION_STEPS:
        raise ValueError(f"diffusion_steps={steps!r}: expected a whole number in [1, {MAX_DIFFUSION_STEPS:,}]")


def training_scheduler(**overrides) -> DDPMScheduler:
    """A DDPM training schedule: ε-prediction, by default cosine betas over T = 1000 (the paper's);
    ``overrides`` (``beta_schedule``, ``num_train_timesteps``, ...) change it (checked: :func:`check_schedule`)."""
    from diffusers import DDPMScheduler

    config = {**TRAIN_SCHEDULER_CONFIG, **overrides}
    if config.get("trained_betas") is None:
        check_schedule(config["beta_schedule"], config["num_train_timesteps"])
    return DDPMScheduler(**config)


@dataclass
class Sampler:
    """A reverse process over the training schedule: ``kind`` (a registered scheduler or ``"module:Class"``,
    module docstring), ``steps`` (default: the kind's, 1000 for ``ddpm``, 50 otherwise), ``eta`` (DDIM only),
    ``clip_x0``."""

    kind: str = "ddim"
    steps: int | None = None
    eta: float = 0.0
    clip_x0: bool = True

    def __post_init__(self):
        from spread.model.schedulers import scheduler_spec

        spec = scheduler_spec(str(self.kind))  # an unknown kind is an error naming the registered ones
        if self.steps is None:
            self.steps = spec.steps
        if not 1 <= self.steps <= TRAIN_SCHEDULER_CONFIG["num_train_timesteps"]:
            raise ValueError(f"sampler steps must be in [1, 1000], got {self.steps}")

    def check_eta(self) -> None:
        """``ValueError`` for an ``eta`` outside [0, 1] (beyond 1 the step's noise exceeds its variance: NaN), or other
        than 0 on a sampler that does not read it (every kind but ``ddim``):
        its samples would be those at eta 0 under a second fingerprint and label. Checked where a run is configured
        (:class:`spread.sampling.SamplingConfig`), not where a recorded sampler is read back."""
        import math

        if isinstance(self.eta, bool) or not isinstance(self.eta, (int, float)) or not math.isfinite(self.eta) \
                or not 0.0 <= float(self.eta) <= 1.0:
            raise ValueError(f"sampler.eta={self.eta!r}: expected a number in [0, 1] (0: deterministic DDIM, 1: "
                             f"DDPM-like noise)")
        if float(self.eta) != 0.0 and self.kind != "ddim":
            raise ValueError(f"sampler.eta={self.eta:g}: only the ddim sampler reads eta ({self.kind} ignores it, so "
                             f"its samples would be the same as at eta 0); leave it at 0 or use sampler=ddim")

    @classmethod
    def from_config(cls, config: "Sampler | Mapping | str | None") -> "Sampler":
        """A Sampler, a mapping of its fields, or its :attr:`label` ("ddpm", "ddim-50", "dpmsolver++-20",
        "ddim-50-eta0.5", "ddim-50-noclip")."""
        if config is None:
            return cls()
        if isinstance(config, Sampler):
            return config
        if isinstance(config, str):
            import re

            found = re.fullmatch(r"(?P<kind>.+?)(?:-(?P<steps>\d+))?(?:-eta(?P<eta>[0-9.eE+-]+))?(?P<noclip>-noclip)?",
                                 config)
            steps, eta = found["steps"], found["eta"]
            return cls(kind=found["kind"], steps=int(steps) if steps else None, eta=float(eta) if eta else 0.0,
                       clip_x0=not found["noclip"])
        return cls(**dict(config))

    @property
    def label(self) -> str:
        """The sampler's one spelling: ``ddim-50``, ``ddpm-1000``, ``ddim-50-eta0.5``, ``dpmsolver++-20-noclip``."""
        return (f"{self.kind}-{self.steps}" + (f"-eta{self.eta:g}" if self.eta else "")
                + ("" if self.clip_x0 else "-noclip"))

    def fingerprint(self) -> dict:
        """Every field (each changes the samples)."""
        return {"kind": self.kind, "steps": int(self.steps), "eta": float(self.eta), "clip_x0": bool(self.clip_x0)}

    @property
    def num_steps(self) -> int:
        return int(self.steps)

    def scheduler(self, schedule: Mapping | None = None):
        """A fresh diffusers scheduler for this sampler, from the config of the schedule the model was trained
        with (``model.noise_schedule.config``, or only the keys that differ from the default training schedule,
        e.g. ``{"beta_schedule": "linear"}``; default: the default training schedule)."""
        from spread.model.schedulers import scheduler_spec

        base = training_scheduler(**{k: v for k, v in dict(schedule or {}).items() if not k.startswith("_")}).config
        return scheduler_spec(self.kind).build(base)
