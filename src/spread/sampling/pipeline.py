"""``ScenePipeline``: conditioning graphs in, posed scenes out — network, sampler, per-step edits and pose
decoding in one object, as a diffusers pipeline holds its model, scheduler and loop. It samples every diffusion
method the same way (SPREAD's variants, DiffuScene, InstructScene: each gives its batch's
:class:`~spread.model.diffusion.Denoising`), through the platform's one loop
(:func:`spread.model.diffusion.denoise`, which model validation uses too).

One call (:meth:`ScenePipeline.__call__`) on a batch of source scenes (the conditioning graphs):

1. **encode** them exactly as in training (:class:`~spread.data.SceneDataset` with the checkpoint's point
   settings) and collate into one padded batch;
2. the method's **denoising problem** (``model.denoising(batch, use_ema, graph_scale)``: its ε-function with EMA
   weights and classifier-free ``graph_scale`` — and ``geometry_scale`` for a model with geometry features
   (``has_geometry``: SPREAD's +Geometry) —, mask, state size, training schedule, differentiable pose
   decoder and its own per-step edit, e.g. DiffuScene's imputation of the known channels);
3. **callbacks** for this batch (:meth:`ScenePipeline.callbacks`, plus any passed in): per-step edits of the
   predicted x̂_0 (``x0_hook``) or of the sampled state (``sample_hook``) and edits after the sampler
   (``after``). Physics guidance is such a callback, for every method alike (its terms act on the decoded
   poses): ``guidance=paper`` steers x̂_0 at every step, ``guidance=sample`` the sampled state (PhyScene's
   ``guidance=physcene``), ``guidance=refine`` refines after the sampler
   (:class:`~spread.guidance.SceneGuidance`, built here with the batch's meshes and support graph);
4. **sample** with :func:`~spread.model.diffusion.denoise` (the :class:`~spread.model.Sampler`'s reverse process,
   one noise generator per scene), **decode** the states to poses (metres, world-from-local) and **repair**
   rotations that Gram–Schmidt left degenerate (:func:`repair_rotations`).

A method that samples its own way (``sampling: own`` in the method registry: ATISS's autoregressive loop) is asked
for poses directly (``model.sample(batch, generator=...)``); step callbacks do not apply to it. A model that reads
more of the source scenes than the batch encoding carries (the SPREAD release's network: its shape tokens, points and
graphs) adds them with ``scene_inputs(sources, library)``; one that realises a guidance mode its own way says so with
``resolve_guidance(config)`` (the release: ``guidance=paper`` is the authors' refinement, mode ``release``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from spread.scene import Scene

#: The network's arithmetic while sampling: float32 throughout, or bfloat16 autocast (the geometry features and the
#: sampler's update stay float32).
PRECISIONS = ("32", "bf16")
#: A sampled rotation further than this from orthonormal (max |RᵀR − I|) is replaced by its nearest rotation.
REPAIR_TOLERANCE = 1e-4


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
    from spread.model.diffusion import SamplingCallback

    config = guidance.config
    if not config.active:
        return None
    if config.mode == "paper":
        return SamplingCallback(x0_hook=guidance.x0_hook)
    if config.mode == "sample":
        return SamplingCallback(sample_hook=guidance.sample_hook)
    return SamplingCallback(after=guidance.refine)


def sampling_kind(model) -> str:
    """How a model samples, from the method registry (its checkpoint's ``method``: ``pipeline`` through this
    pipeline's loop and callbacks, or ``own`` through its own ``sample``); a model of no registered method:
    ``pipeline`` when it has ``denoising``."""
    from spread.methods.registry import METHODS

    hparams = getattr(model, "hparams", None) or {}
    method = str(hparams.get("method") or ("spread" if hasattr(model, "denoising") else ""))
    if method in METHODS:
        return METHODS.get(method).sampling
    return "pipeline" if hasattr(model, "denoising") else "own"


#: ``sampling.cuda_graph=null`` records a batch's step only when its loop calls the network at least this often:
#: recording costs about three calls (two warm-up, one recorded), which a short schedule would not earn back.
AUTO_GRAPH_MIN_CALLS = 10


def resolve_cuda_graph(setting: bool | None, capturable: bool | None, calls: int = AUTO_GRAPH_MIN_CALLS) -> bool:
    """``sampling.cuda_graph`` for a model whose ``cuda_graph_capturable`` is ``capturable`` (None: the model does not
    say) and a loop of ``calls`` network calls: the setting when given, else (null) on only for a model that says its
    step reads nothing on the host, in a loop of at least :data:`AUTO_GRAPH_MIN_CALLS`."""
    if setting is None:
        return capturable is True and calls >= AUTO_GRAPH_MIN_CALLS
    if not isinstance(setting, bool):
        raise ValueError(f"sampling.cuda_graph must be true, false or null (the model's own), got {setting!r}")
    return setting


def check_values(graph_scale, geometry_scale, precision: str) -> tuple[float, float]:
    """The sampling settings that need no model, refused in one line (``ValueError``) when they cannot be sampled
    with: each guidance scale a finite number, ``precision`` one of :data:`PRECISIONS`; returns the two scales as
    floats. Checked where a :class:`spread.sampling.SamplingConfig` is made and by every :class:`ScenePipeline`."""
    import math

    scales = []
    for name, value in (("graph_scale", graph_scale), ("geometry_scale", geometry_scale)):
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = float("nan")
        if isinstance(value, bool) or not math.isfinite(number):
            raise ValueError(f"{name}={value}: a finite number (1: the model as trained)")
        scales.append(number)
    if precision not in PRECISIONS:
        raise ValueError(f"sampling precision must be one of {PRECISIONS}, got '{precision}'")
    return scales[0], scales[1]


class ScenePipeline:
    """A trained model, its data encoder, a sampler and a guidance config (module docstring).

    model: a :class:`~spread.model.SceneDiffusion`, a baseline, any module with ``denoising`` (or ``sample``),
    in eval mode on its device. dataset: the :class:`~spread.data.SceneDataset` that encodes graphs (its
    asset library gives guidance its meshes). sampler: a :class:`~spread.model.Sampler` or its config.
    guidance: a :class:`~spread.guidance.GuidanceConfig`, its mapping, or None (unguided).
    """

    def __init__(self, model, dataset, sampler, guidance=None, use_ema: bool = True, graph_scale: float = 1.0,
                 cuda_graph: bool | None = None, precision: str = "32", geometry_scale: float = 1.0):
        from spread.guidance import GuidanceConfig
        from spread.model import Sampler

        graph_scale, geometry_scale = check_values(graph_scale, geometry_scale, precision)
        if geometry_scale != 1.0 and not getattr(model, "has_geometry", False):
            hparams = getattr(model, "hparams", {})
            kind = ", ".join(f"{k} {hparams[k]}" for k in ("method", "variant") if k in hparams) or type(model).__name__
            raise ValueError(f"geometry_scale={geometry_scale}: this model ({kind}) has no geometry features to guide; "
                             f"sample it with geometry_scale=1")
        self.model, self.dataset = model, dataset
        self.sampler = Sampler.from_config(sampler)
        config = GuidanceConfig.from_config(guidance)
        if config.active and hasattr(model, "resolve_guidance"):  # the method's own realisation of a mode
            config = model.resolve_guidance(config)
        self.guidance = config if config.active else None
        self.use_ema, self.graph_scale, self.geometry_scale = bool(use_ema), graph_scale, geometry_scale
        capturable = getattr(model, "cuda_graph_capturable", None)  # None: the method does not say
        if cuda_graph is True and capturable is False:
            raise ValueError(f"sampling.cuda_graph=true: a '{getattr(model, 'method', type(model).__name__)}' model's "
                             f"step cannot be captured as a CUDA graph (it reads tensors on the host at every step); "
                             f"sample it with cuda_graph=false")
        self.cuda_graph_setting = cuda_graph
        # null: where the model says its step can be recorded and the loop is long enough; on CUDA only (on_device)
        self.cuda_graph = resolve_cuda_graph(cuda_graph, capturable, self.network_calls())
        self.precision = str(precision)
        self.guidance_stats: dict = {}

    def network_calls(self) -> int:
        """Network calls of a batch's loop: the sampler's steps and, in ``refine``/``release`` mode, one per
        denoising projection of the guidance's iterations."""
        calls = int(self.sampler.steps)
        g = self.guidance
        if g is not None and g.mode in ("refine", "release") and g.denoise_every:
            calls += -(-int(g.iterations) // int(g.denoise_every))
        return calls

    def encode(self, sources: Sequence[Scene], paths: Sequence[str] | None = None) -> dict:
        """The collated batch of ``sources`` (encoded as in training)."""
        from spread.data import collate_scenes

        paths = paths or [None] * len(sources)
        return collate_scenes([self.dataset.encode(src, source=path) for src, path in zip(sources, paths)])

    def callbacks(self, batch: dict, sources: Sequence[Scene], problem=None) -> list:
        """This batch's callbacks: physics guidance when the pipeline guides, with the batch's meshes, steering the
        states of ``problem`` (the method's :class:`~spread.model.diffusion.Denoising`; its decoder gives the
        terms their poses — SPREAD's 9-d states are decoded by the guidance itself, bit for bit as before)."""
        if self.guidance is None:
            return []
        from spread.guidance import SceneGuidance

        import torch

        from spread.scene import welded_objects

        device = self.model.device
        welded = torch.zeros(batch["mask"].shape, dtype=torch.bool)
        for b, src in enumerate(sources):
            welded[b, batch["mask"][b].cpu().bool()] = torch.from_numpy(welded_objects(src))  # the real objects' slots
        state_dim = 9 if problem is None else problem.state_dim
        # 9-d states are SPREAD's (translation, rot6d): the guidance decodes them itself; others by their method
        decode = None if state_dim == 9 else (lambda x: tuple(problem.decode(x)))
        guidance = SceneGuidance(self.guidance, self.dataset.library, [list(src.asset_id) for src in sources],
                                 batch["physical"].to(device), batch["mask"].to(device), self.model.bounds,
                                 alpha_bar0=float(self.model.noise_schedule.alphas_cumprod[0]), welded=welded,
                                 decode=decode, state_dim=state_dim, lead=0 if problem is None else problem.lead)
        self._last_guidance = guidance
        callback = guidance_callback(guidance)
        return [callback] if callback is not None else []

    def sample_states(self, batch: dict, generator=None, callbacks: Sequence[SamplingCallback] = (),
                      sources: Sequence[Scene] | None = None):
        """States (B, N, C) after the sampler and every callback, and the mask (B, N); with ``sources`` the
        pipeline's own callbacks (guidance) run before ``callbacks``."""
        x, problem = self._sample(batch, generator, callbacks, sources)
        return x, problem.mask

    def _sample(self, batch, generator, callbacks, sources):
        import torch

        from spread.model.diffusion import denoise

        with torch.no_grad():
            # geometry_scale only when set: methods without geometry features do not take it (refused above)
            extra = {"geometry_scale": self.geometry_scale} if self.geometry_scale != 1.0 else {}
            problem = self.model.denoising(batch, self.use_ema, self.graph_scale, **extra)
        problem = self.on_device(problem)
        own = self.callbacks(batch, sources, problem) if sources is not None else []
        return denoise(problem, self.sampler, generator, [*own, *callbacks]), problem

    def on_device(self, problem):
        """The problem's ε-function in the pipeline's ``precision`` (``bf16``: autocast on the model's device) and,
        with ``cuda_graph`` on a CUDA device, captured once and replayed every step
        (:class:`~spread.model.capture.GraphedStep`)."""
        import dataclasses

        import torch

        fn = problem.eps_fn
        device = problem.mask.device
        if self.precision == "bf16":
            inner = fn

            def fn(x, t):
                # no autocast weight cache: a CUDA graph records the casts with the rest of the call
                with torch.autocast(device.type, dtype=torch.bfloat16, cache_enabled=False):
                    return inner(x, t).float()
        if self.cuda_graph and device.type == "cuda":
            from spread.model.capture import GraphedStep

            if self.cuda_graph_setting is None:  # the default: eager again, with a warning, where it cannot record
                model = self.model
                fn = GraphedStep(fn, check=lambda: getattr(model, "cuda_graph_capturable", False) is True,
                                 fallback=True)
            else:
                fn = GraphedStep(fn)
        return problem if fn is problem.eps_fn else dataclasses.replace(problem, eps_fn=fn)

    def __call__(self, sources: Sequence[Scene], generators, paths: Sequence[str] | None = None,
                 callbacks: Sequence[SamplingCallback] = ()) -> list[SampledPoses]:
        """Poses for every source scene (one ``torch.Generator`` per scene: its noise ignores the batch);
        ``callbacks``: per-step edits of this call, after the pipeline's guidance."""
        import torch

        batch = self.encode(sources, paths)
        if hasattr(self.model, "scene_inputs"):  # arrays the model reads from the source scenes (the release's)
            batch.update(self.model.scene_inputs(sources, self.dataset.library))
        self._last_guidance = None
        pipelined = sampling_kind(self.model) == "pipeline"
        problem = None
        if pipelined:
            x, problem = self._sample(batch, generators, callbacks, sources)
            with torch.no_grad():
                poses = problem.decode(x)
        else:
            poses = self.model.sample(batch, sampler=self.sampler, generator=generators, use_ema=self.use_ema)
        self.guidance_stats = dict(self._last_guidance.stats) if self._last_guidance is not None else {}
        translation, rotation = poses.translation.cpu().numpy(), poses.rotation.cpu().numpy()
        timeline = self.timeline(problem)
        out = []
        for b, src in enumerate(sources):
            n = src.num_objects
            R, repaired = repair_rotations(rotation[b, :n])
            track = None if timeline is None else (timeline[0][:, b, :n], timeline[1][:, b, :n])
            out.append(SampledPoses(translation[b, :n], R, repaired, track))
        return out

    def timeline(self, problem) -> tuple[np.ndarray, np.ndarray] | None:
        """The recorded guidance states decoded to poses: translation (T, B, N, 3), rotation (T, B, N, 3, 3)."""
        guidance = self._last_guidance
        if problem is None or guidance is None or not guidance.trajectory:
            return None
        import torch

        with torch.no_grad():
            decoded = [problem.decode(x) for x in guidance.trajectory]
        return (np.stack([d.translation.cpu().numpy() for d in decoded]),
                np.stack([d.rotation.cpu().numpy() for d in decoded]))
