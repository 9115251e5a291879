"""``ScenePipeline``: conditioning graphs in, posed scenes out — network, sampler, per-step edits and pose
decoding in one object, as a diffusers pipeline holds its model, scheduler and loop.

One call (:meth:`ScenePipeline.__call__`) on a batch of source scenes (the conditioning graphs):

1. **encode** them exactly as in training (:class:`~spread.data.SceneDataset` with the checkpoint's point
   settings) and collate into one padded batch;
2. **callbacks** for this batch (:meth:`ScenePipeline.callbacks`): per-step edits of the predicted x̂_0
   (``x0_hook``, run at every sampler step) and edits after the sampler (``after``). Physics guidance is
   such a callback: ``guidance=paper`` steers x̂_0 at every step, ``guidance=refine`` refines after the
   sampler (:class:`~spread.guidance.SceneGuidance`, built here with the batch's meshes and support graph);
3. **sample**: the model's ε-function for the batch (``model.denoiser``: EMA weights, classifier-free
   ``graph_scale``), the :class:`~spread.model.Sampler`'s reverse process with one noise generator per
   scene, then the ``after`` callbacks;
4. **decode** the states to poses (``model.decode``: metres, world-from-local) and **repair** rotations
   that Gram–Schmidt left degenerate (:func:`repair_rotations`).

A model without ``denoiser`` (an autoregressive baseline) is asked for poses directly
(``model.sample(batch, generator=...)``); step callbacks do not apply to it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from spread.scene import Scene

#: A sampled rotation further than this from orthonormal (max |RᵀR − I|) is replaced by its nearest rotation.
REPAIR_TOLERANCE = 1e-4


@dataclass
class SamplingCallback:
    """A per-batch edit of the sampling: ``x0_hook(x0, ctx) → x0`` at every sampler step (ctx:
    :class:`~spread.model.StepContext`), ``after(x, eps_fn) → x`` once after the sampler."""

    x0_hook: Callable | None = None
    after: Callable | None = None


@dataclass
class SampledPoses:
    """One scene's sampled poses: translation (N, 3) metres, rotation (N, 3, 3), rotations repaired."""

    translation: np.ndarray
    rotation: np.ndarray
    repaired: int
    #: the guidance timeline (``guidance.record_every``): translation (T, N, 3) metres, rotation (T, N, 3, 3)
    trajectory: tuple[np.ndarray, np.ndarray] | None = None


def repair_rotations(rotation: np.ndarray) -> tuple[np.ndarray, int]:
    """(N, 3, 3) rotations with the degenerate ones replaced by the nearest proper rotation (SVD); and how
    many were replaced. Gram–Schmidt of a sampled rot6d whose two columns are (anti)parallel — e.g. both
    clipped to (±1, ±1, ±1) by an undertrained model — leaves a zero column, which no reader accepts."""
    R = rotation.astype(np.float64)
    error = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
    bad = np.flatnonzero((error > REPAIR_TOLERANCE) | (np.linalg.det(R) <= 0))
    if not len(bad):
        return rotation, 0
    U, _, Vt = np.linalg.svd(R[bad])
    D = np.ones((len(bad), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    D[D[:, 2] == 0, 2] = 1.0
    out = rotation.copy()
    out[bad] = ((U * D[:, None, :]) @ Vt).astype(rotation.dtype)
    return out, len(bad)


def guidance_callback(guidance) -> SamplingCallback | None:
    """The callback of a :class:`~spread.guidance.SceneGuidance`: ``paper`` mode edits x̂_0 at every step,
    ``refine`` mode refines after the sampler; None when it does not guide (mode ``none``, no weight > 0)."""
    config = guidance.config
    if not config.active:
        return None
    if config.mode == "paper":
        return SamplingCallback(x0_hook=guidance.x0_hook)
    return SamplingCallback(after=guidance.refine)


def sampling_kind(model) -> str:
    """How a model samples, from the method registry (its checkpoint's ``method``: ``pipeline`` through this
    pipeline's loop and callbacks, or ``own`` through its own ``sample``); a model of no registered method:
    ``pipeline`` when it has a ``denoiser``."""
    from spread.baselines.registry import METHODS

    hparams = getattr(model, "hparams", None) or {}
    method = str(hparams.get("method") or ("spread" if hasattr(model, "denoiser") else ""))
    if method in METHODS:
        return METHODS.get(method).sampling
    return "pipeline" if hasattr(model, "denoiser") else "own"


def chain_hooks(hooks: Sequence[Callable]) -> Callable | None:
    """One x̂_0 hook applying ``hooks`` in order (None when there are none)."""
    hooks = [h for h in hooks if h is not None]
    if not hooks:
        return None

    def hook(x0, ctx):
        for h in hooks:
            x0 = h(x0, ctx)
        return x0

    return hook


class ScenePipeline:
    """A trained model, its data encoder, a sampler and a guidance config (module docstring).

    model: a :class:`~spread.model.SceneDiffusion` (or a module with ``denoiser``/``decode``, or ``sample``),
    in eval mode on its device. dataset: the :class:`~spread.data.SceneDataset` that encodes graphs (its
    asset library gives guidance its meshes). sampler: a :class:`~spread.model.Sampler` or its config.
    guidance: a :class:`~spread.guidance.GuidanceConfig`, its mapping, or None (unguided).
    """

    def __init__(self, model, dataset, sampler, guidance=None, use_ema: bool = True, graph_scale: float = 1.0):
        from spread.guidance import GuidanceConfig
        from spread.model import Sampler

        self.model, self.dataset = model, dataset
        self.sampler = Sampler.from_config(sampler)
        config = GuidanceConfig.from_config(guidance)
        self.guidance = config if config.active else None
        self.use_ema, self.graph_scale = bool(use_ema), float(graph_scale)
        self.guidance_stats: dict = {}

    def encode(self, sources: Sequence[Scene], paths: Sequence[str] | None = None) -> dict:
        """The collated batch of ``sources`` (encoded as in training)."""
        from spread.data import collate_scenes

        paths = paths or [None] * len(sources)
        return collate_scenes([self.dataset.encode(src, source=path) for src, path in zip(sources, paths)])

    def callbacks(self, batch: dict, sources: Sequence[Scene]) -> list:
        """This batch's callbacks: physics guidance when the pipeline guides, with the batch's meshes."""
        if self.guidance is None:
            return []
        from spread.guidance import SceneGuidance

        import torch

        from spread.scene import welded_objects

        device = self.model.device
        welded = torch.zeros(batch["mask"].shape, dtype=torch.bool)
        for b, src in enumerate(sources):
            welded[b, batch["mask"][b].cpu().bool()] = torch.from_numpy(welded_objects(src))  # the real objects' slots
        guidance = SceneGuidance(self.guidance, self.dataset.library, [list(src.asset_id) for src in sources],
                                 batch["physical"].to(device), batch["mask"].to(device), self.model.network.bounds,
                                 alpha_bar0=float(self.model.noise_schedule.alphas_cumprod[0]), welded=welded)
        self._last_guidance = guidance
        callback = guidance_callback(guidance)
        return [callback] if callback is not None else []

    def sample_states(self, batch: dict, generator=None, callbacks: Sequence[SamplingCallback] = ()):
        """Normalised states (B, N, 9) of the batch, after the sampler and the ``after`` callbacks."""
        import torch

        with torch.no_grad():
            eps_fn, mask = self.model.denoiser(batch, self.use_ema, self.graph_scale)
            x = self.sampler.sample(eps_fn, mask, generator=generator, x0_hook=chain_hooks([c.x0_hook for c in callbacks]),
                                    schedule=self.model.noise_schedule.config)
            for c in callbacks:
                if c.after is not None:
                    x = c.after(x, eps_fn)
        return x, mask

    def __call__(self, sources: Sequence[Scene], generators, paths: Sequence[str] | None = None) -> list[SampledPoses]:
        """Poses for every source scene (one ``torch.Generator`` per scene: its noise ignores the batch)."""
        batch = self.encode(sources, paths)
        self._last_guidance = None
        if sampling_kind(self.model) == "pipeline":
            x, mask = self.sample_states(batch, generators, self.callbacks(batch, sources))
            poses = self.model.decode(x, mask)
        else:
            if hasattr(self.model, "scene_inputs"):  # arrays the model reads from the source scenes (the release's)
                batch.update(self.model.scene_inputs(sources, self.dataset.library))
            poses = self.model.sample(batch, sampler=self.sampler, generator=generators, use_ema=self.use_ema)
        self.guidance_stats = dict(self._last_guidance.stats) if self._last_guidance is not None else {}
        translation, rotation = poses.translation.cpu().numpy(), poses.rotation.cpu().numpy()
        timeline = self.timeline(mask if sampling_kind(self.model) == "pipeline" else None)
        out = []
        for b, src in enumerate(sources):
            n = src.num_objects
            R, repaired = repair_rotations(rotation[b, :n])
            track = None if timeline is None else (timeline[0][:, b, :n], timeline[1][:, b, :n])
            out.append(SampledPoses(translation[b, :n], R, repaired, track))
        return out

    def timeline(self, mask) -> tuple[np.ndarray, np.ndarray] | None:
        """The recorded guidance states decoded to poses: translation (T, B, N, 3), rotation (T, B, N, 3, 3)."""
        guidance = self._last_guidance
        if mask is None or guidance is None or not guidance.trajectory:
            return None
        import torch

        with torch.no_grad():
            decoded = [self.model.decode(x, mask) for x in guidance.trajectory]
        return (np.stack([d.translation.cpu().numpy() for d in decoded]),
                np.stack([d.rotation.cpu().numpy() for d in decoded]))
