"""``GuidanceConfig``: which guided-sampling mode runs, the three weights and their schedule.

Modes (reference notes §3.1, paper §3.4):

========== ========================================================================================
``none``   no guidance; sampling is exactly the unguided sampler's
``paper``  the paper's equation: at every denoising step (from ``start`` on) the predicted x̂_0 takes
           one step ``x̂_0 ← x̂_0 − Σ_k λ_k ∇G_k(x̂_0)`` before the sampler uses it
``refine`` the release's behaviour: after sampling, ``iterations`` refinement iterations at t = 0,
           each a denoising projection with the network then the same gradient step
``sample`` PhyScene's placement: after every sampler step (from ``start`` on, or the last ``last_steps``)
           the sampled state x_{t−1} takes the gradient step (``guidance=physcene``: its box-IoU term on
           the last 10 steps, each term's step clipped to ±``grad_clip``)
``release`` the authors' code as released: ``refine``'s loop with the release's own three terms
           (:mod:`spread.guidance.release`: its cone frames, its one-ray gravity against every other
           object, its support hulls fixed at the first iteration); what ``guidance=paper`` runs for the
           authors' checkpoint (``method: release``)
========== ========================================================================================

Weights: every registered term (:mod:`spread.guidance.terms`: the built-ins, PhyScene's ``box_iou``, a plugin's)
is weighed by name, ``guidance.terms.<name>=λ``; the built-in terms' weights also have keys of their own
(``guidance.collision`` is ``guidance.terms.collision``), the paper's λ (``collision`` 7.5e-3, ``gravity`` 1e-3,
``relation`` 1e-3). Applied in normalised state space (translation in [−1, 1] through the dataset bounds, rot6d) as the release does
(its λ × lr = 15 × 5e-4, 2 × 5e-4, 2 × 5e-4). Gravity joins only from ``gravity_from`` of the way
through (fraction of the sampling steps in ``paper`` mode, of the refinement iterations in ``refine``
mode; the release: the later half of its 100 iterations). Geometry constants are in metres.

A config is the setting's one identity: :meth:`GuidanceConfig.weights` (every registered term's λ),
:attr:`~GuidanceConfig.active`, :attr:`~GuidanceConfig.label` and :meth:`~GuidanceConfig.fingerprint` are what
sampling, tags, tables, reports and the done-check (:mod:`spread.runtime.fingerprint`) ask; none re-derives them.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from dataclasses import field
from typing import Any, Mapping

MODES = ("none", "paper", "refine", "sample", "release")
DETECT = ("auto", "host", "device")
#: Field metadata of a weight key: the field is the weight of the registered term of its name.
TERM = {"term": True}
#: Settings read by some modes only (:class:`~spread.guidance.SceneGuidance`: ``refine`` and ``release`` run its
#: refinement loop, ``paper`` and ``sample`` its per-step hook); under another mode they change nothing, so they
#: are no part of its identity (:meth:`GuidanceConfig.settings`).
READ_BY = {"iterations": ("refine", "release"), "denoise_every": ("refine", "release"), "clip": ("refine", "release"),
           "start": ("paper", "sample"), "last_steps": ("paper", "sample"), "inner_steps": ("paper", "sample")}


def without_unread(settings: dict) -> dict:
    """A guidance identity's settings (flat, with its ``mode``) without those its mode does not read (:data:`READ_BY`);
    an identity recorded before they were left out reads the same (:func:`spread.runtime.fingerprint.upgraded`)."""
    mode = settings.get("mode")
    return {k: v for k, v in settings.items() if k not in READ_BY or mode in READ_BY[k]}


@dataclass
class GuidanceConfig:
    """Guided-sampling settings (module docstring). Units: weights are step sizes in normalised
    state space; ``cone_height``, ``gap``, ``tolerance`` are metres."""

    mode: str = "none"
    #: λ_C, λ_H, λ_R of the paper: the weights of the built-in terms of these names (keys of their own, aliases
    #: of ``terms.<name>``; :meth:`weight_keys`).
    collision: float = field(default=7.5e-3, metadata=TERM)
    gravity: float = field(default=1e-3, metadata=TERM)
    relation: float = field(default=1e-3, metadata=TERM)
    #: ``refine``: refinement iterations at t = 0 after the sampler (release: 100).
    iterations: int = 100
    #: ``refine``: the t = 0 denoising projection runs every this many iterations (1 = every one, the
    #: release; 0 = never: guidance steps only). Each projection is one network call on the batch.
    denoise_every: int = 1
    #: ``paper`` / ``sample``: guidance applies from step ``ceil(start · steps)`` on (0 = every step, the equation).
    start: float = 0.0
    #: ``paper`` / ``sample``: when > 0, guidance applies at the last this many sampling steps only (instead of
    #: ``start``; PhyScene: 10).
    last_steps: int = 0
    #: Each term's step λ·∇G is clipped to ±this per value (0 = not clipped; PhyScene: 0.1).
    grad_clip: float = 0.0
    #: Gravity joins from this fraction of the steps / iterations on (release: 0.5).
    gravity_from: float = 0.5
    #: ``paper``: gradient steps per guided sampling step.
    inner_steps: int = 1
    #: CoDF cone height h (metres; release 0.5).
    cone_height: float = 0.5
    #: Gravity: ε, the gap an object keeps above what it rests on (release 5e-4 m).
    gap: float = 5e-4
    #: Gravity: θ_H, the tolerated extra gap before an object counts as floating (release 2e-3 m).
    tolerance: float = 2e-3
    #: Settle (``terms.settle``, not the paper's): its downward rays start at least this far above an object's lowest
    #: point (metres), so that an object the network sank into its supporter — a book 12 cm into a mattress, a
    #: plate into a table top past its own centre — still sees the surface it belongs on and is lifted onto it.
    settle_reach: float = 0.15
    #: Collision: factor on the upward part of the collision step on the y channel (release 3).
    up_boost: float = 3.0
    #: Gravity moves only the y translation (release); False keeps its full gradient.
    gravity_y_only: bool = True
    #: Most triangle pairs reported per object pair by the BVH query (bounds the cost when objects
    #: interpenetrate wholesale, as early predictions of x̂_0 do).
    max_contacts: int = 2048
    #: Where the geometry the terms differentiate through is found (colliding triangle pairs, supporters'
    #: footprints): ``host`` (python-fcl and scipy on CPU copies of the poses), ``device`` (tensor operations where
    #: the states are: :mod:`spread.guidance.dense`), ``auto`` (the device's path on CUDA, the host's on the CPU).
    #: The same pairs and footprints either way, but for triangles that only touch (tests).
    detect: str = "auto"
    #: ``refine``: clip the t = 0 projection to [−1, 1] (what the release's scheduler step does).
    clip: bool = True
    #: Weights of the registered terms by name (:mod:`spread.guidance.terms`: plugins, PhyScene's ``box_iou``),
    #: e.g. ``guidance.terms.box_iou=0.15``; ``terms.collision`` sets the key ``collision`` above.
    terms: dict[str, float] = field(default_factory=dict)
    #: Keep the states every this many guidance iterations (``refine``) or guided steps (``paper``), first and
    #: last included, in each sample's file as ``trajectory_translation`` / ``trajectory_rotation`` (the
    #: guidance timeline ``spread-view`` plays); 0: none.
    record_every: int = 0

    def __post_init__(self):
        if self.mode not in MODES:
            raise ValueError(f"guidance: key 'mode' is {self.mode!r}, choose from {MODES}")
        if self.detect not in DETECT:
            raise ValueError(f"guidance: key 'detect' is {self.detect!r}, choose from {DETECT}")
        own = self.weight_keys()
        self.terms = {str(k): v for k, v in dict(self.terms or {}).items()}
        for name in [n for n in self.terms if n in own]:  # terms.collision is the key collision
            setattr(self, name, self.terms.pop(name))
        for key in (*own, "cone_height", "gap", "tolerance", "settle_reach", "up_boost", "grad_clip"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"guidance: key '{key}' must be a finite number ≥ 0, got {value!r}")
        if self.cone_height <= 0:
            raise ValueError(f"guidance: key 'cone_height' must be > 0, got {self.cone_height!r}")
        for key in ("start", "gravity_from"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
                raise ValueError(f"guidance: key '{key}' must be a fraction in [0, 1], got {value!r}")
        settings = {f.name for f in dataclasses.fields(self)}
        for name, value in self.terms.items():
            if name in settings:
                raise ValueError(f"guidance: 'terms.{name}': a term cannot be named like the setting '{name}'")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ValueError(f"guidance: key 'terms.{name}' must be a finite number ≥ 0, got {value!r}")
            if value > 0:
                from spread.guidance.terms import TERMS_REGISTRY

                TERMS_REGISTRY.get(name)  # an unknown term is an error naming the known ones
        for key, low in (("iterations", 0), ("denoise_every", 0), ("inner_steps", 1), ("max_contacts", 1),
                         ("record_every", 0), ("last_steps", 0)):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"guidance: key '{key}' must be an integer ≥ {low}, got {value!r}")

    # ---- the setting's identity -------------------------------------------------------------------------
    @classmethod
    def weight_keys(cls) -> tuple[str, ...]:
        """The terms whose weight has a key of its own (the built-ins; ``guidance.<name>``)."""
        return tuple(f.name for f in dataclasses.fields(cls) if f.metadata.get("term"))

    def weight(self, name: str) -> float:
        """λ of the term ``name`` (its own key, else ``terms.<name>``; 0 when this config does not weigh it)."""
        if name in self.weight_keys():
            return float(getattr(self, name))
        return float(self.terms.get(name, 0.0))

    def weights(self, nonzero: bool = False) -> dict[str, float]:
        """λ of every registered term by name, in registry order (built-ins, PhyScene's, plugins'), then any other
        name the config weighs; ``nonzero``: only the terms with λ > 0."""
        from spread.guidance.terms import TERMS_REGISTRY

        names = [*TERMS_REGISTRY.names(), *[n for n in self.terms if n not in TERMS_REGISTRY]]
        out = {name: TERMS_REGISTRY.get(name).weight_of(self) if name in TERMS_REGISTRY else self.weight(name)
               for name in names}
        return {k: v for k, v in out.items() if v > 0} if nonzero else out

    def settings(self) -> dict:
        """Every setting other than the weights (mode, schedule, geometry constants, ...) that the mode reads
        (:data:`READ_BY`: ``iterations`` set under ``paper`` resampled every scene to the same bytes)."""
        own = self.weight_keys()
        return without_unread({k: v for k, v in self.to_dict().items() if k not in own and k != "terms"})

    @property
    def active(self) -> bool:
        """True when sampling is guided at all: a mode other than ``none`` and some registered term's λ > 0."""
        return self.mode != "none" and bool(self.weights(nonzero=True))

    def fingerprint(self) -> dict | None:
        """What a guided sample depends on, flat: the mode, λ of every term that acts (by its name) and every
        other setting; None when unguided (its weights change nothing)."""
        if not self.active:
            return None
        return {**self.settings(), **self.weights(nonzero=True)}

    @property
    def label(self) -> str:
        """``none``, or the mode with each acting term's λ and each setting that differs from the defaults:
        ``refine(collision=0.0075,gravity=0.001,relation=0.001)``, ``sample(box_iou=0.15,last_steps=10,grad_clip=0.1)``."""
        if not self.active:
            return "none"
        default = GuidanceConfig(mode=self.mode).settings()
        parts = [f"{k}={v:g}" for k, v in self.weights(nonzero=True).items()]
        parts += [f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in self.settings().items()
                  if k != "mode" and v != default.get(k)]
        return f"{self.mode}({','.join(parts)})"

    def first_step(self, steps: int) -> int:
        """The first guided step of a ``paper`` or ``sample`` loop of ``steps`` steps (``last_steps``, else
        ``start``)."""
        if self.last_steps > 0:
            return max(0, steps - self.last_steps)
        return math.ceil(self.start * steps)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_config(cls, config: "GuidanceConfig | Mapping | str | None") -> "GuidanceConfig":
        """A GuidanceConfig, a mapping of its fields (a Hydra node too), a mode name, or None (``none``).

        Unknown keys are an error naming them; integral floats (``iterations: 100.0``) are accepted.
        """
        if config is None:
            return cls()
        if isinstance(config, GuidanceConfig):
            return config
        if isinstance(config, str):
            return cls(mode=config)
        if not isinstance(config, Mapping):
            raise TypeError(f"guidance: expected a mode name, a mapping or a GuidanceConfig, "
                            f"got {type(config).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        values: dict[str, Any] = {}
        for key, value in dict(config).items():
            if key not in fields:
                raise ValueError(f"guidance: unknown key '{key}' (known: {', '.join(fields)})")
            if fields[key].type == "int" and isinstance(value, float) and value.is_integer():
                value = int(value)
            if fields[key].type == "float" and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            values[key] = value
        return cls(**values)
