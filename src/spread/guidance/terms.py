"""The guidance-term registry: each differentiable term defined once, switched on by name with a weight.

A :class:`GuidanceTerm` is a name, a loss (``loss(ctx) → (B,)`` per-scene values at the states of a
:class:`TermContext`, differentiable in ``ctx.x``), how its weight is read from the
:class:`~spread.guidance.GuidanceConfig`, its **schedule** (``start(config)``: the fraction of the sampling steps,
or of the refinement iterations, from which it acts) and an optional edit of its gradient. The built-in terms
register themselves in their modules, as ordinary terms: ``collision`` (the upward boost), ``gravity`` (from
``guidance.gravity_from``, y only) and ``relation``; their weights also have keys of their own
(``guidance.collision``, an alias of ``guidance.terms.collision``). Any registered term is switched on with
``guidance.terms.<name>=<weight>``,
the same way for every method that samples through :class:`~spread.sampling.ScenePipeline` (PhyScene's box-IoU
term is ``guidance.terms.box_iou``).

A term from another package is an entry point in the group ``spread.guidance`` naming a :class:`GuidanceTerm`
or a plain function ``loss(ctx) → (B,)`` (then: weight from ``guidance.terms``, acting at every step).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from spread.registry import Registry, RegistryError


@dataclass(frozen=True)
class GuidanceTerm:
    """One guidance term (module docstring). weight: ``weight(config) → λ`` (default the config's weight of its name,
    :meth:`~spread.guidance.GuidanceConfig.weight`: ``guidance.terms.<name>``, 0 when absent); start: ``start(config) → fraction`` of the loop from which it acts (default 0); edit:
    ``edit(grad, config) → grad`` applied to its gradient before weighting (default none)."""

    name: str
    loss: Callable[["TermContext"], torch.Tensor]
    weight: Callable | None = None
    start: Callable | None = None
    edit: Callable | None = None
    description: str = ""

    def weight_of(self, config) -> float:
        if self.weight is not None:
            return float(self.weight(config))
        return float(config.weight(self.name))

    def start_of(self, config) -> float:
        return 0.0 if self.start is None else float(self.start(config))


def _adapt(name: str, obj) -> GuidanceTerm:
    if isinstance(obj, GuidanceTerm):
        return obj if obj.name == name else GuidanceTerm(**{**obj.__dict__, "name": name})
    if callable(obj):
        return GuidanceTerm(name, obj, description=(obj.__doc__ or "").strip().split("\n")[0])
    raise RegistryError(f"guidance entry point '{name}': expected a GuidanceTerm or a function loss(ctx) → (B,), "
                        f"got {obj!r}")


TERMS_REGISTRY: Registry[GuidanceTerm] = Registry("guidance term", "spread.guidance", packages=("spread.guidance",),
                                                  adapt=_adapt)


def register_term(term: GuidanceTerm) -> GuidanceTerm:
    """Register a built-in or run-time term under its name."""
    return TERMS_REGISTRY.register(term.name, term, origin=getattr(term.loss, "__module__", ""))


def term_names() -> list[str]:
    return TERMS_REGISTRY.names()


class TermContext:
    """What a term sees at one evaluation: states ``x`` (B, N, 9), their poses (``translation`` (B, N, 3) metres,
    ``rotation`` (B, N, 3, 3)), the posed mesh vertices ``world`` and hull points ``hull`` (metres), the batch's
    :class:`~spread.guidance.meshes.SceneMeshes`, ``mask`` (B, N), ``supports`` (B, N, N: row supports column),
    ``falls`` (B, N: objects gravity acts on; wall and ceiling mounts do not fall), ``held`` (support pairs whose
    supported object is not welded), ``support_pairs`` / ``held_pairs`` (their True entries as (S, 3) [b, i, j] rows,
    found once per sample), ``bounds`` (6,), the config, and :meth:`pairs` (the BVH's colliding triangle
    pairs, found once per context)."""

    def __init__(self, guidance, x: torch.Tensor, translation, rotation, world, hull, graph: dict):
        self.guidance, self.x = guidance, x
        self.translation, self.rotation, self.world, self.hull = translation, rotation, world, hull
        self.meshes, self.config = guidance.meshes, guidance.config
        self.mask, self.supports, self.bounds = graph["mask"], graph["supports"], graph["bounds"]
        self.falls, self.held = graph["falls"], graph["held"]
        # (S, 3) [b, i, j] rows of supports / held, found once per sample (None: a caller without them)
        self.support_pairs, self.held_pairs = graph.get("support_pairs"), graph.get("held_pairs")
        self.detach_cones = guidance.detach_cones
        #: whether the non-differentiable geometry is found on the states' device (``guidance.detect``)
        self.on_device = guidance.on_device(x.device)
        self._pairs = None

    def pairs(self):
        """:class:`~spread.guidance.collision.TrianglePairs` between different objects at these poses."""
        if self._pairs is None:
            self._pairs = self.guidance.detect(self.translation, self.rotation, self.hull, self.world)
        return self._pairs
