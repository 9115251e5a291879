"""``SceneGuidance``: the registered guidance terms of a batch of scenes and the two guided-sampling modes.

One guidance step on normalised states x (B, N, C) — SPREAD's 9-d states (translation in [−1, 1] through
``bounds``, rot6d; :func:`spread.model.poses.poses_from_state`), or any method's states with its ``decode``
(DiffuScene's and InstructScene's centre, size, cos θ, sin θ: every term acts on the decoded poses, so each
method is guided the same way) — is, as in the release,

    x ← x − Σ_k [k on] λ_k edit_k(∇G_k)      (built-ins: λ_C ∇G_C + λ_H ∇G_H + λ_R ∇G_R)

over the terms of the registry (:mod:`spread.guidance.terms`) whose weight is > 0, each summed over scenes (so
a scene's step never depends on the rest of its batch), switched on by its schedule (gravity from
``gravity_from``) and, with ``grad_clip`` > 0, clipped to ±``grad_clip`` per value (PhyScene's clip). The release's two tweaks are the built-ins' gradient edits, on by default (config): the
upward part of the collision step on the normalised-y channel is multiplied by ``up_boost`` (3), and the
gravity step is kept on the y channel only. Padding objects never move.

``paper`` mode plugs :meth:`SceneGuidance.x0_hook` into the sampler: at sampling step k of K (from
``ceil(start·K)`` on, or the last ``last_steps``) the predicted x̂_0 takes ``inner_steps`` steps, gravity from
``ceil(gravity_from·K)``. ``sample`` mode (:meth:`SceneGuidance.sample_hook`) takes the same steps on the
sampled state x_{t−1} after the sampler's step (PhyScene's placement).
``refine`` mode (:meth:`SceneGuidance.refine`) runs after the sampler: ``iterations`` times, ε̂ =
eps_fn(x, t = 0), x ← clip((x − √(1−ᾱ_0) ε̂)/√ᾱ_0, ±1) (the denoising projection the release's
scheduler step takes at t = 0, ᾱ_0 of the training schedule; every ``denoise_every``-th iteration,
1 = always as the release), then one step, gravity from ``ceil(gravity_from·iterations)``.
``release`` mode is ``refine``'s loop with the release's own terms (:mod:`spread.guidance.release`) in place of the
built-in collision, gravity and relation. States may carry ``lead`` entries before the objects (the release's
placeholder at index 0): the projection denoises them, no term sees them, no step moves them.
:attr:`SceneGuidance.stats` records where the time went.
"""

from __future__ import annotations

import math
import time
from typing import Callable, Sequence

import torch

from spread.guidance.collision import TriangleCollider, TrianglePairs
from spread.guidance.config import GuidanceConfig
from spread.guidance.dense import resolve_detect, triangle_pairs
from spread.guidance.meshes import SceneMeshes
from spread.guidance.release import RELEASE_TERMS
from spread.guidance.terms import TERMS_REGISTRY, GuidanceTerm, TermContext
from spread.model.diffusion import StepContext, training_scheduler
from spread.model.poses import poses_from_state

#: Normalised-y channel of a state (translation x, y, z then rot6d).
Y_CHANNEL = 1


class SceneGuidance:
    """Guidance for a batch of B scenes padded to N objects.

    config: anything :meth:`GuidanceConfig.from_config` takes. library: the
    :class:`~spread.assets.AssetLibrary`. asset_ids: per scene, its real objects' asset ids in object
    order (they fill the True slots of ``mask``). physical: (B, N, N) physical codes (1 = row supports
    column; padding 3). mask: (B, N) bool. bounds: (6,) translation bounds, metres (stats.json).
    alpha_bar0: ᾱ_0 of the model's training schedule (``refine``'s t = 0 projection; default: the default
    schedule's). welded: (B, N) bool, the wall and ceiling mounts (:func:`spread.scene.welded_objects`):
    gravity and support (relation) guidance leave them alone (no gap to close, no footprint to be pulled
    over); default none. decode: ``x (B, N, C) → (translation (B, N, 3) metres, rotation (B, N, 3, 3))``,
    differentiable, the method's state decoder (default SPREAD's 9-d states through ``bounds``); state_dim: C.
    lead: entries before the objects in every state (states (B, lead + N, C); the release's placeholder: 1),
    which ``decode`` drops: the projection of ``refine`` denoises them, no step moves them.
    """

    def __init__(self, config, library, asset_ids: Sequence[Sequence[str]], physical: torch.Tensor,
                 mask: torch.Tensor, bounds, detach_cones: bool = True, alpha_bar0: float | None = None,
                 welded: torch.Tensor | None = None, decode: Callable | None = None, state_dim: int = 9,
                 lead: int = 0):
        self.config = GuidanceConfig.from_config(config)
        self.mask = torch.as_tensor(mask).bool().cpu()
        if self.mask.dim() != 2:
            raise ValueError(f"guidance: mask must be (B, N), got {tuple(self.mask.shape)}")
        B, N = self.mask.shape
        physical = torch.as_tensor(physical).cpu()
        if tuple(physical.shape) != (B, N, N):
            raise ValueError(f"guidance: physical must be (B, N, N) = {(B, N, N)}, got {tuple(physical.shape)}")
        self.bounds = torch.as_tensor(bounds, dtype=torch.float64).flatten().cpu()
        lo, hi = self.bounds[:3], self.bounds[3:]
        if self.bounds.numel() != 6 or not torch.isfinite(self.bounds).all() or (hi <= lo).any():
            raise ValueError(f"guidance: bounds must be 6 finite numbers [min xyz, max xyz] with max > min, "
                             f"got {self.bounds.tolist()}")
        pair = self.mask[:, :, None] & self.mask[:, None, :] & ~torch.eye(N, dtype=torch.bool)
        self.supports = (physical == 1) & pair
        self.welded = torch.zeros(B, N, dtype=torch.bool) if welded is None else torch.as_tensor(welded).bool().cpu()
        if tuple(self.welded.shape) != (B, N):
            raise ValueError(f"guidance: welded must be (B, N) = {(B, N)}, got {tuple(self.welded.shape)}")
        self.meshes = SceneMeshes(library, asset_ids, self.mask)
        self._collider: TriangleCollider | None = None  # python-fcl's objects, made on the host path's first use
        self.detach_cones = detach_cones
        self.decode, self.state_dim, self.lead = decode, int(state_dim), int(lead)
        if self.lead < 0 or (self.lead and decode is None):
            raise ValueError(f"guidance: lead {lead}: leading entries need the method's decode, which drops them")
        #: what a term keeps across the steps of this batch (the release's first-iteration hulls)
        self.cache: dict = {}
        self.alpha_bar0 = float(training_scheduler().alphas_cumprod[0]) if alpha_bar0 is None else float(alpha_bar0)
        self._on: dict[tuple, dict[str, torch.Tensor]] = {}
        #: states (B, lead + N, C) kept every ``config.record_every`` iterations or guided steps (the timeline)
        self.trajectory: list[torch.Tensor] = []
        self.reset_stats()

    # ---- bookkeeping --------------------------------------------------------------------------------
    def reset_stats(self) -> None:
        self._stats = {"bvh_s": 0.0, "penalty_s": 0.0, "network_s": 0.0, "steps": 0, "iterations": 0,
                       "network_calls": 0, "object_pairs": 0, "colliding_pairs": 0, "last_colliding_pairs": 0}

    @property
    def stats(self) -> dict:
        """Seconds in BVH detection (``bvh_s``: broad phase + fcl), in the differentiable terms and their
        gradients (``penalty_s``), in the network during refinement (``network_s``); guidance ``steps``,
        refinement ``iterations``, ``network_calls``, object pairs given to fcl and triangle pairs found
        (both summed over steps), and the triangle pairs of the last step."""
        return dict(self._stats)

    def _graph(self, device: torch.device, dtype: torch.dtype) -> dict[str, torch.Tensor]:
        key = (str(device), dtype)
        hit = self._on.get(key)
        if hit is None:
            lead = torch.ones(self.mask.shape[0], self.lead, dtype=torch.bool)
            hit = self._on[key] = {"mask": self.mask.to(device), "supports": self.supports.to(device),
                                   "moves": torch.cat([~lead, self.mask], 1).to(device),  # what a step moves
                                   "states": torch.cat([lead, self.mask], 1).to(device),  # what the loop keeps
                                   "bounds": self.bounds.to(device, dtype),
                                   "falls": (self.mask & ~self.welded).to(device),
                                   "held": (self.supports & ~self.welded[:, None, :]).to(device)}
            # the support pairs as (S, 3) [b, i, j] rows, found once on the host (not a device read every step)
            hit["support_pairs"] = self.supports.nonzero().to(device)
            hit["held_pairs"] = (self.supports & ~self.welded[:, None, :]).nonzero().to(device)
        return hit

    # ---- terms --------------------------------------------------------------------------------------
    def term(self, name: str) -> GuidanceTerm:
        """The registered term ``name``; in ``release`` mode the release's own collision, gravity and relation."""
        if self.config.mode == "release" and name in RELEASE_TERMS:
            return RELEASE_TERMS[name]
        return TERMS_REGISTRY.get(name)

    def on_device(self, device: torch.device) -> bool:
        """Whether the terms' geometry is found on ``device`` itself (``guidance.detect`` resolved for it)."""
        return resolve_detect(self.config.detect, device) == "device"

    def detect(self, translation: torch.Tensor, rotation: torch.Tensor, hull: torch.Tensor,
               world: torch.Tensor | None = None) -> TrianglePairs:
        """The colliding triangle pairs at these poses (``hull`` (B, N, H, 3): the posed hull vertices, whose
        boxes are the broad phase; ``world``: the posed vertices, which the device path needs)."""
        t0 = time.perf_counter()
        if world is not None and self.on_device(world.device):
            g = self._graph(world.device, world.dtype)
            h = hull.detach()
            pairs = triangle_pairs(world, self.meshes, h.amin(2), h.amax(2), g["mask"], self.config.max_contacts)
        else:
            lo = hull.detach().amin(2).cpu().double().numpy()
            hi = hull.detach().amax(2).cpu().double().numpy()
            if self._collider is None:
                self._collider = TriangleCollider(self.meshes, self.config.max_contacts)
            pairs = self._collider.find(rotation.detach().cpu().double().numpy(),
                                       translation.detach().cpu().double().numpy(), lo, hi, self.mask.numpy())
        self._stats["bvh_s"] += time.perf_counter() - t0
        self._stats["object_pairs"] += pairs.object_pairs
        self._stats["colliding_pairs"] += len(pairs)
        self._stats["last_colliding_pairs"] = len(pairs)
        return pairs

    def _terms(self, x: torch.Tensor, which: Sequence[str]) -> dict[str, torch.Tensor]:
        """Per-scene values (B,) of the named registered terms at states x (differentiable when x requires grad)."""
        g = self._graph(x.device, x.dtype)
        if self.decode is None:
            translation, rotation = poses_from_state(x, g["bounds"])
        else:
            translation, rotation = self.decode(x)
            translation, rotation = translation.to(x.dtype), rotation.to(x.dtype)
        world = self.meshes.pose(translation, rotation)
        hull = self.meshes.hull_points(world)
        ctx = TermContext(self, x, translation, rotation, world, hull, g)
        out = {}
        for name in which:
            term = self.term(name)
            if name == "collision":
                ctx.pairs()  # the BVH's time is counted apart (bvh_s)
            t0 = time.perf_counter()
            out[name] = term.loss(ctx)
            self._stats["penalty_s"] += time.perf_counter() - t0
        return out

    def losses(self, x: torch.Tensor, reduce: bool = True, which: Sequence[str] | None = None) -> dict[str, torch.Tensor]:
        """Each term's value at states x (B, N, C): summed over scenes (``reduce``) or per scene (B,); ``which``:
        the registered terms' names (default the built-ins and every term the config weighs).
        Differentiable when x requires grad (cones, hulls and hit heights detached; module docs)."""
        self._check(x)
        names = list(which) if which is not None else [*GuidanceConfig.weight_keys(), *self.config.terms]
        values = self._terms(x, names)
        return {k: v.sum() if reduce else v for k, v in values.items()}

    def _check(self, x: torch.Tensor) -> None:
        B, N = self.mask.shape
        if x.dim() != 3 or tuple(x.shape[:2]) != (B, self.lead + N) or x.shape[-1] != self.state_dim:
            shape = f"(B, N, {self.state_dim})" if not self.lead else f"(B, {self.lead} + N, {self.state_dim})"
            raise ValueError(f"guidance: states must be {shape} with (B, N) = {(B, N)}"
                             f"{f' (leading entries: {self.lead})' if self.lead else ''}, got {tuple(x.shape)}")

    # ---- one step -----------------------------------------------------------------------------------
    def weights(self, at: tuple[int, int] | None = None, late: bool = True) -> dict[str, float]:
        """λ of every registered term that acts now, in registry order: weight > 0 and its schedule started —
        ``at`` = (index, count) of the loop (a term starting at fraction s acts from index ``ceil(s·count)``), or
        without ``at``: terms with a start > 0 act when ``late`` (the gravity flag of older callers)."""
        cfg = self.config
        out = {}
        for name, weight in cfg.weights(nonzero=True).items():
            start = self.term(name).start_of(cfg)
            if at is not None:
                index, count = at
                on = index >= math.ceil(start * count)
            else:
                on = late or start <= 0
            if on:
                out[name] = weight
        return out

    def step(self, x: torch.Tensor, gravity: bool = True, at: tuple[int, int] | None = None) -> torch.Tensor:
        """One guidance step on states x (B, N, C) (module docstring); returns new states, x untouched.
        ``at``: (index, count) in the loop for the terms' schedules; else ``gravity`` switches the late terms."""
        self._check(x)
        cfg = self.config
        weights = self.weights(at, gravity)
        which = list(weights)
        if not which:
            return x
        with torch.enable_grad():
            xg = x.detach().clone().requires_grad_(True)
            values = self._terms(xg, which)
            t0 = time.perf_counter()
            update = torch.zeros_like(x)
            for n, name in enumerate(which):
                loss = values[name].sum()
                if not loss.requires_grad:
                    continue
                (grad,) = torch.autograd.grad(loss, xg, retain_graph=n < len(which) - 1)
                edit = self.term(name).edit
                if edit is not None:
                    grad = edit(grad, cfg)
                grad = weights[name] * grad
                if cfg.grad_clip > 0:  # PhyScene clips each value of its step
                    grad = torch.nan_to_num(grad, nan=0.0, posinf=0.0, neginf=0.0).clamp(-cfg.grad_clip, cfg.grad_clip)
                update = update + grad
            self._stats["penalty_s"] += time.perf_counter() - t0
        self._stats["steps"] += 1
        keep = self._graph(x.device, x.dtype)["moves"][..., None].to(x.dtype)
        return (x - torch.nan_to_num(update, nan=0.0, posinf=0.0, neginf=0.0) * keep).detach()

    # ---- the two modes ------------------------------------------------------------------------------
    def x0_hook(self, x0: torch.Tensor, ctx: StepContext) -> torch.Tensor:
        """``paper`` mode: guide the predicted x̂_0 of sampling step ``ctx.index`` of ``ctx.num_steps``."""
        return self._guide_step(x0, ctx)

    def sample_hook(self, x: torch.Tensor, ctx: StepContext) -> torch.Tensor:
        """``sample`` mode: guide the sampled state x_{t−1} after sampling step ``ctx.index``."""
        return self._guide_step(x, ctx)

    def _guide_step(self, x: torch.Tensor, ctx: StepContext) -> torch.Tensor:
        K, k = ctx.num_steps, ctx.index
        first = self.config.first_step(K)
        if k < first:
            return x
        self._record(x, k - first, first=k == first)
        for _ in range(self.config.inner_steps):
            x = self.step(x, at=(k, K))
        if k == K - 1:
            self._record(x, None, last=True)
        return x

    def _record(self, x: torch.Tensor, index: int | None, first: bool = False, last: bool = False) -> None:
        every = self.config.record_every
        if every and (first or last or (index is not None and index % every == 0)):
            self.trajectory.append(x.detach().clone())

    def refine(self, x: torch.Tensor, eps_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> torch.Tensor:
        """``refine`` (and ``release``) mode: ``iterations`` × (t = 0 denoising projection with ``eps_fn``,
        guidance step)."""
        self._check(x)
        n = self.config.iterations
        keep = self._graph(x.device, x.dtype)["states"][..., None].to(x.dtype)
        a = self.alpha_bar0
        if x.dtype != torch.float64:  # as the release's scheduler step: √ᾱ_0, √(1 − ᾱ_0) of its float32 ᾱ_0, in float32
            a32 = torch.tensor(a, dtype=torch.float32)
            root_a, root_b = float(a32 ** 0.5), float((1 - a32) ** 0.5)
        else:
            root_a, root_b = a ** 0.5, (1 - a) ** 0.5
        t_zero = torch.zeros(x.shape[0], dtype=torch.long, device=x.device)
        every = self.config.denoise_every
        self._record(x, 0, first=True)
        for it in range(n):
            if every and it % every == 0:
                t0 = time.perf_counter()
                with torch.no_grad():
                    eps = eps_fn(x, t_zero).to(x.dtype) * keep
                self._stats["network_s"] += time.perf_counter() - t0
                self._stats["network_calls"] += 1
                x = (x - root_b * eps) / root_a
                if self.config.clip:
                    x = x.clamp(-1.0, 1.0)
            x = self.step(x * keep, at=(it, n))
            self._stats["iterations"] += 1
            if it + 1 < n:
                self._record(x, it + 1)
        self._record(x, None, last=True)
        return x
