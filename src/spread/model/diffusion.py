"""Noise schedules (diffusers) and the sampler: a training schedule, three interchangeable samplers.

Training: ``DDPMScheduler(num_train_timesteps, beta_schedule, prediction_type="epsilon")`` with the model's
``diffusion_steps`` and ``beta_schedule`` (:class:`~spread.model.config.SceneDiffusionConfig`; the paper's
1,000 steps of ``squaredcos_cap_v2`` by default, :data:`TRAIN_SCHEDULER_CONFIG`); x_t = ``add_noise(x_0, ε, t)``.

:class:`Sampler` — chosen by config, independent of the model, built from the model's training schedule
(``schedule``: its scheduler config; the default schedule when not given), its ``kind`` a registered scheduler
(:mod:`spread.model.schedulers`: ``ddpm``, by default over all 1000 steps as the release runs; ``ddim`` with
``eta``; ``dpmsolver++``; a plugin's) or a diffusers scheduler class as ``"module:Class"``. Each call builds a
fresh scheduler (they are stateful). A sampler has one spelling, its :attr:`Sampler.label` (``ddim-50``,
``ddpm-1000``, ``ddim-50-eta0.5``), which :meth:`Sampler.from_config` reads back. Its settings live in the
torch-free :mod:`spread.model.sampler` (re-exported here); its loop is :func:`reverse_process`.

The loop (:func:`reverse_process`) works on any ``eps_fn(x_t, t) -> ε̂``; every diffusion method samples through
it by one function, :func:`denoise`, which takes a method's :class:`Denoising` (its ε-function, mask, state size,
training schedule, pose decoder and own per-step edit) and the injected :class:`SamplingCallback` s (guidance,
per-step edits): SPREAD's model, its validation, DiffuScene, InstructScene and
:class:`~spread.sampling.ScenePipeline` all call it. For SPREAD the model's closure
recomputes the geometry features from x_t at every step. Each step it forms the predicted
x̂_0 = (x_t − √(1−ᾱ_t) ε̂)/√ᾱ_t, clips it to [−1, 1] (``clip_x0``; all 9 channels live there),
applies ``x0_hook(x̂_0, ctx)`` if given (guidance plugs in here), turns x̂_0 back into the ε the
scheduler steps with, then applies ``sample_hook(x_{t−1}, ctx)`` if given. Padding objects are
held at 0 throughout (initial noise, every ε̂ and every sample are multiplied by the mask), so they
never influence real ones. Randomness comes only from ``generator``: same seed, same samples. A list
of B generators (one per scene) makes each scene's noise independent of its batch-mates: with the
deterministic samplers (DDIM with eta = 0, DPM-Solver++) a scene samples the same in any batch, up to float
rounding; ancestral ones (DDPM, DDIM with eta > 0) draw each step's noise per scene but at the batch's padded
size, so there a sample also depends on how far its batch is padded.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Mapping

import torch

# the sampler's settings live in a torch-free module (a command refuses a bad setting before torch loads); they
# are re-exported here, where the loop is
from spread.model.sampler import SAMPLER_KINDS, TRAIN_SCHEDULER_CONFIG, Sampler, training_scheduler  # noqa: F401

if TYPE_CHECKING:  # diffusers loads with the first scheduler
    from diffusers import DDPMScheduler

#: What the network predicts (diffusers' names): the noise ε, the clean state x_0, or v = √ᾱ ε − √(1−ᾱ) x_0
#: (Salimans & Ho 2022). Samplers and guidance always receive ε (:func:`epsilon_from_prediction`).
PREDICTIONS = ("epsilon", "sample", "v_prediction")
#: Per-timestep loss weights: none (plain MSE on the prediction), min_snr (Hang et al. 2023, min(SNR, γ)
#: expressed for the prediction target).
LOSS_WEIGHTINGS = ("none", "min_snr")
#: Per-scene initial noise is drawn as (max(N, NOISE_ROWS), state_dim) and cut to N, so a scene's x_T does not
#: depend on how far its batch is padded (torch's CPU normal sampler fills large tensors in another order).
NOISE_ROWS = 64


def check_prediction(prediction: str) -> str:
    if prediction not in PREDICTIONS:
        raise ValueError(f"unknown prediction '{prediction}' (choose from {PREDICTIONS})")
    return prediction


def prediction_target(prediction: str, x0: torch.Tensor, noise: torch.Tensor, alpha_bar: torch.Tensor) -> torch.Tensor:
    """The training target of a network that predicts ``prediction`` for x_t = √ᾱ x_0 + √(1−ᾱ) ε;
    x0, noise (B, N, C), alpha_bar (B,) ᾱ_t of each scene's timestep."""
    check_prediction(prediction)
    if prediction == "epsilon":
        return noise
    if prediction == "sample":
        return x0
    a = alpha_bar.to(x0)[:, None, None]
    return a.sqrt() * noise - (1 - a).sqrt() * x0


def epsilon_from_prediction(prediction: str, output: torch.Tensor, x_t: torch.Tensor,
                            alpha_bar: torch.Tensor) -> torch.Tensor:
    """ε̂ from the network's output (B, N, C) at states x_t (B, N, C) with ᾱ_t (B,): the identity for
    ``epsilon``, ε = (x_t − √ᾱ x̂_0)/√(1−ᾱ) for ``sample``, ε = √(1−ᾱ) x_t + √ᾱ v̂ for ``v_prediction``."""
    check_prediction(prediction)
    if prediction == "epsilon":
        return output
    a = alpha_bar.to(device=x_t.device, dtype=torch.float64)[:, None, None]
    x, out = x_t.double(), output.double()
    if prediction == "sample":
        eps = (x - a.sqrt() * out) / (1 - a).clamp(min=1e-12).sqrt()
    else:
        eps = (1 - a).sqrt() * x + a.sqrt() * out
    return eps.to(output.dtype)


def x0_from_prediction(prediction: str, output: torch.Tensor, x_t: torch.Tensor,
                       alpha_bar: torch.Tensor) -> torch.Tensor:
    """The network's x̂_0 (B, N, C) from its output at states x_t (B, N, C) with ᾱ_t (B,), differentiable in the
    output: the output itself for ``sample``, (x_t − √(1−ᾱ) ε̂)/√ᾱ for ``epsilon``, √ᾱ x_t − √(1−ᾱ) v̂ for
    ``v_prediction``."""
    check_prediction(prediction)
    if prediction == "sample":
        return output
    a = alpha_bar.to(output)[:, None, None]
    if prediction == "epsilon":
        return (x_t - (1 - a).sqrt() * output) / a.sqrt().clamp_min(1e-6)
    return a.sqrt() * x_t - (1 - a).sqrt() * output


def loss_weights(weighting: str, prediction: str, alpha_bar: torch.Tensor, gamma: float = 5.0) -> torch.Tensor:
    """(B,) per-scene loss weights for timesteps with ᾱ_t ``alpha_bar`` (B,). ``min_snr``: the weight that
    makes each target's MSE equal min(SNR, γ)·‖x̂_0 − x_0‖² (Hang et al. 2023): min(SNR, γ)/SNR for ε,
    min(SNR, γ) for x_0, min(SNR, γ)/(SNR + 1) for v; SNR = ᾱ/(1 − ᾱ)."""
    check_prediction(prediction)
    if weighting not in LOSS_WEIGHTINGS:
        raise ValueError(f"unknown loss weighting '{weighting}' (choose from {LOSS_WEIGHTINGS})")
    if weighting == "none":
        return torch.ones_like(alpha_bar)
    snr = alpha_bar / (1 - alpha_bar)
    clipped = snr.clamp(max=gamma)
    if prediction == "epsilon":
        return clipped / snr
    if prediction == "sample":
        return clipped
    return clipped / (snr + 1)


@dataclass
class StepContext:
    """What a hook sees at one sampling step."""

    index: int  # 0 … num_steps − 1
    num_steps: int
    timestep: int  # the training timestep t of this step
    x_t: torch.Tensor  # (B, N, 9) the current noisy state
    eps: torch.Tensor  # (B, N, 9) the model's ε̂
    mask: torch.Tensor  # (B, N) bool
    alpha_bar: float  # ᾱ_t


Hook = Callable[[torch.Tensor, StepContext], torch.Tensor]


@dataclass
class SamplingCallback:
    """An injected edit of one batch's sampling: ``x0_hook(x̂_0, ctx) → x̂_0`` at every sampler step (ctx:
    :class:`StepContext`), ``sample_hook(x_{t−1}, ctx) → x_{t−1}`` after every sampler step, ``after(x, eps_fn)
    → x`` once after the sampler."""

    x0_hook: Hook | None = None
    sample_hook: Hook | None = None
    after: Callable | None = None


@dataclass
class Denoising:
    """What a diffusion method hands the one loop for a batch (``model.denoising(batch, use_ema, graph_scale)``).

    eps_fn: ``(x_t (B, N, C), t (B,)) → ε̂``; mask: (B, N) bool real objects; state_dim: C; schedule: the config of
    the method's training noise schedule; decode: ``x (B, N, C) → Poses`` (translation (B, N, 3) metres,
    rotation (B, N, 3, 3) world-from-local), differentiable in x, so guidance terms defined on poses steer any
    method — a state's first three channels are the translation normalised by the dataset bounds (the
    collision boost and gravity's y-only edit act on channel 1); x0_hook: the method's own per-step edit of
    x̂_0, run before any callback's (DiffuScene's and InstructScene's imputation of the known channels);
    finish: ``x → x`` after the sampler and every callback (the imputation once more); lead: entries before the
    objects in every state (the SPREAD release's placeholder at index 0: states (B, 1 + N, C), ``mask`` True there):
    the loop denoises them, ``decode`` drops them (poses (B, N, ...)), guidance never moves them."""

    eps_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
    mask: torch.Tensor
    decode: Callable
    state_dim: int = 9
    schedule: Mapping | None = None
    x0_hook: Hook | None = None
    finish: Callable | None = None
    lead: int = 0


def chain_hooks(hooks) -> Hook | None:
    """One hook applying ``hooks`` (None entries skipped) in order; None when there are none."""
    hooks = [h for h in hooks if h is not None]
    if not hooks:
        return None
    if len(hooks) == 1:
        return hooks[0]

    def hook(x, ctx):
        for h in hooks:
            x = h(x, ctx)
        return x

    return hook


def denoise(problem: Denoising, sampler, generator=None, callbacks=()) -> torch.Tensor:
    """The one sampling loop of every diffusion method: the reverse process of ``problem`` (a :class:`Denoising`)
    with ``sampler`` (a :class:`Sampler` or what :meth:`Sampler.from_config` takes), noise from ``generator``
    (one per scene: a list), the method's own x̂_0 edit then the ``callbacks``' x̂_0 and sample edits in list
    order at every step, their ``after`` edits in list order once after the sampler, then ``problem.finish``.
    Returns the states (B, N, C), zero at padding, autograd off."""
    callbacks = [c for c in callbacks if c is not None]
    with torch.no_grad():
        x = reverse_process(
            Sampler.from_config(sampler), problem.eps_fn, problem.mask, generator=generator,
            x0_hook=chain_hooks([problem.x0_hook, *[c.x0_hook for c in callbacks]]),
            sample_hook=chain_hooks([c.sample_hook for c in callbacks]), state_dim=problem.state_dim,
            schedule=problem.schedule)
        for c in callbacks:
            if c.after is not None:
                x = c.after(x, problem.eps_fn)
        if problem.finish is not None:
            x = problem.finish(x)
    return x


def ddpm_step(scheduler: DDPMScheduler, eps: torch.Tensor, t: int, x: torch.Tensor,
              noise: torch.Tensor | None) -> torch.Tensor:
    """diffusers' ``DDPMScheduler.step`` (ε-prediction, no clipping: our loop clips x̂_0 itself) with the step's
    noise given (None: the last, noiseless step), its arithmetic as diffusers does it — the same host scalars in
    the same order — so the states are the ones ``scheduler.step(..., generator=...)`` gives for that noise."""
    prev_t = scheduler.previous_timestep(t)
    alpha_prod_t = scheduler.alphas_cumprod[t]
    alpha_prod_t_prev = scheduler.alphas_cumprod[prev_t] if prev_t >= 0 else scheduler.one
    beta_prod_t = 1 - alpha_prod_t
    beta_prod_t_prev = 1 - alpha_prod_t_prev
    current_alpha_t = alpha_prod_t / alpha_prod_t_prev
    current_beta_t = 1 - current_alpha_t
    pred_original_sample = (x - beta_prod_t ** (0.5) * eps) / alpha_prod_t ** (0.5)
    pred_original_sample_coeff = (alpha_prod_t_prev ** (0.5) * current_beta_t) / beta_prod_t
    current_sample_coeff = current_alpha_t ** (0.5) * beta_prod_t_prev / beta_prod_t
    prev = pred_original_sample_coeff * pred_original_sample + current_sample_coeff * x
    if t > 0 and noise is not None:
        prev = prev + (scheduler._get_variance(t) ** 0.5) * noise
    return prev


@torch.no_grad()
def reverse_process(sampler: Sampler, eps_fn: Callable[[torch.Tensor, torch.Tensor], torch.Tensor], mask: torch.Tensor,
                    generator: torch.Generator | list[torch.Generator] | None = None, x0_hook: Hook | None = None,
                    sample_hook: Hook | None = None, state_dim: int = 9, dtype: torch.dtype = torch.float32,
                    schedule: Mapping | None = None) -> torch.Tensor:
    """``sampler``'s reverse process for scenes ``mask`` (B, N) → x̂_0 (B, N, state_dim), zero at padding (the loop
    every method samples through, by :func:`denoise`); ``schedule``: the training schedule's config, as in
    :meth:`Sampler.scheduler`.

    Hooks run with autograd off; a guidance hook that needs gradients enables them itself
    (``torch.enable_grad()``).
    """
    mask = mask.bool()
    device = mask.device
    keep = mask[..., None].to(dtype)
    scheduler = sampler.scheduler(schedule)
    if sampler.num_steps > scheduler.config.num_train_timesteps:
        raise ValueError(f"sampler steps {sampler.num_steps} > the model's {scheduler.config.num_train_timesteps} "
                         f"training timesteps")
    # the schedule stays on the host: a step's coefficients are host numbers, so no step reads the device
    scheduler.set_timesteps(sampler.num_steps)
    timesteps = [int(t) for t in scheduler.timesteps]
    alphas = scheduler.alphas_cumprod.double()
    B, N = mask.shape
    per_scene = isinstance(generator, (list, tuple))
    if per_scene:  # one generator per scene: a scene's noise ignores its batch
        if len(generator) != B:
            raise ValueError(f"reverse_process: {len(generator)} generators for a batch of {B}")
        rows = max(N, NOISE_ROWS)  # a fixed-size draw: the same first rows at any padding
        draws = [torch.randn((rows, state_dim), generator=g, device=g.device, dtype=dtype)[:N] for g in generator]
        x = torch.stack([d.to(draws[0].device) for d in draws])  # one copy to the device, not one per scene
        generator = list(generator)
    else:
        noise_device = generator.device if generator is not None else device
        x = torch.randn((*mask.shape, state_dim), generator=generator, device=noise_device, dtype=dtype)
    x = x.to(device) * keep
    # ancestral samplers' per-step noise, drawn up front in the order the scheduler would draw it (per scene:
    # after its x_T, one (1, N, C) draw per noisy step) and moved to the device once
    ancestral = sampler.kind == "ddpm" or (sampler.kind == "ddim" and sampler.eta > 0)
    noise = None
    if ancestral and per_scene:
        noisy = [i for i, t in enumerate(timesteps) if sampler.kind == "ddim" or t > 0]
        drawn = torch.stack([torch.cat([torch.randn((1, N, state_dim), generator=g, device=g.device, dtype=dtype)
                                        for _ in noisy]) for g in generator], 1) if noisy else None
        noise = {} if drawn is None else dict(zip(noisy, drawn.to(device).unbind(0)))
    for index, t in enumerate(timesteps):
        t_batch = torch.full((B,), t, device=device, dtype=torch.long)
        eps = eps_fn(x, t_batch).to(dtype) * keep
        a = float(alphas[t])
        ctx = StepContext(index, len(timesteps), t, x, eps, mask, a)
        if sampler.clip_x0 or x0_hook is not None:
            x0 = (x - (1 - a) ** 0.5 * eps) / a ** 0.5
            if sampler.clip_x0:
                x0 = x0.clamp(-1.0, 1.0)
            if x0_hook is not None:
                x0 = x0_hook(x0, ctx)
            eps = (x - a ** 0.5 * x0) / (1 - a) ** 0.5 * keep
        if noise is not None and sampler.kind == "ddpm":
            x = ddpm_step(scheduler, eps, t, x, noise.get(index))
        elif noise is not None:
            x = scheduler.step(eps, t, x, eta=sampler.eta, variance_noise=noise[index]).prev_sample
        else:
            extra = {"eta": sampler.eta} if sampler.kind == "ddim" else {}
            x = scheduler.step(eps, t, x, generator=generator, **extra).prev_sample
        x = x.to(dtype) * keep
        if sample_hook is not None:
            x = sample_hook(x, ctx) * keep
    return x
