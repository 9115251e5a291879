"""``SceneDiffusion``: the LightningModule that trains, validates and samples one variant.

* Loss: MSE of the network's ``prediction`` (ε by default, the paper's; or x_0, or v) over the 9 channels of
  the real objects only (padding excluded from numerator and denominator), each scene weighted by
  ``loss_weighting`` of its timestep (none, or min-SNR), t ~ U{0, …, T−1}, x_t from the model's DDPM training
  schedule (``beta_schedule``, ``diffusion_steps`` = T; the paper's cosine schedule over 1,000 by default,
  :mod:`spread.model.diffusion`). Whatever it predicts, :meth:`SceneDiffusion.denoiser` hands samplers and
  guidance ε̂.
  With ``penetration_weight`` λ > 0, plus λ × the ᾱ_t-weighted box overlap of the decoded x̂_0 beyond the
  training scene's (and ``support_weight`` × the support pairs' rest-height and footprint error; metres,
  :mod:`spread.model.penetration`; and ``spatial_weight`` × the pairs' distance from their spatial codes,
  :mod:`spread.model.spatial_term`; and ``parts_weight`` × the decoded objects' depth inside each other's convex
  parts beyond the training scene's, :mod:`spread.model.parts_term`); ``val/loss`` stays the MSE alone.
* Optimiser: AdamW (lr 1e-4, weight decay 1e-4, paper supplement) on the network's weights; optional linear
  warm-up and cosine decay to the trainer's ``max_steps`` (``lr_warmup_steps``, ``lr_schedule``).
* ``init_from``: a checkpoint whose EMA weights start every weight they have (a ``geometry`` model from a
  trained ``base`` one), loaded at the start of fitting (a resumed run then restores its own state).
* EMA of the weights (:class:`~spread.model.ema.EMA`, a submodule: in the checkpoint, restored on
  resume); validation and :meth:`SceneDiffusion.sample` use it by default.
* Classifier-free guidance training: with probability ``graph_dropout`` a scene's two graphs are
  replaced by padding codes; ``sample(..., graph_scale=s)`` then mixes ε̂ = ε̂_∅ + s (ε̂_G − ε̂_∅).
  ``denoising(..., geometry_scale=s)`` does the same with a +Geometry model's geometry features: the output with
  them against the output reading a scene where nothing is near anything (:meth:`SceneDiffusion.network_output`).
* Validation: ``val/loss`` with seeded noise and timesteps (comparable across epochs); every
  ``sample_every_n_epochs`` epochs (0 = never) the first ``val_sample_scenes`` scenes of the first
  validation batch are sampled with ``val_sampler`` — through the one loop every method samples with
  (:func:`spread.model.diffusion.denoise` on :meth:`SceneDiffusion.denoising`) — and scored with graph recall
  (``val/grecall``, :mod:`spread.model.recall`).
* ``bounds`` (stats.json ``bounds_translations``) are needed to pose objects; when not given they are
  read at ``setup`` from the trainer's datamodule folder (``<root>/stats.json``) and saved with the
  checkpoint.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import NamedTuple, Sequence

import lightning as L
import torch

from spread.data.collate import pad_objects
from spread.model.config import ModelConfig, SceneDiffusionConfig
from spread.model.diffusion import (Denoising, Hook, Sampler, SamplingCallback, check_prediction, denoise,
                                    epsilon_from_prediction, loss_weights, prediction_target, training_scheduler,
                                    x0_from_prediction)
from spread.model.sampler import check_schedule
from spread.model.ema import EMA
from spread.model.layers import round_up
from spread.model.network import SceneDenoiser, sharing_geometry, upgrade_state_dict
from spread.model.geometry import UNCOMPILABLE
from spread.model.parts_distance import PartPlanes
from spread.model.parts_term import parts_excess
from spread.model.penetration import penetration_excess, support_error
from spread.model.poses import poses_from_state
from spread.model.recall import graph_recall
from spread.model.spatial_term import spatial_excess
from spread.scene import PHYSICAL_SUPPORT


class Poses(NamedTuple):
    """Sampled poses: translation (B, N, 3) metres (0 at padding), rotation (B, N, 3, 3) world-from-local
    (identity at padding)."""

    translation: torch.Tensor
    rotation: torch.Tensor


def masked_mse(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor,
               weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared error over the real objects' channels; prediction/target (B, N, C), mask (B, N);
    ``weights`` (B,) scale each scene's squared errors (the denominator stays the count of real channels)."""
    keep = mask[..., None].to(prediction.dtype)
    squared = ((prediction - target) ** 2 * keep).sum((1, 2))
    if weights is not None:
        squared = squared * weights.to(squared)
    return squared.sum() / (keep.sum() * prediction.shape[-1]).clamp(min=1)


LR_SCHEDULES = ("constant", "cosine")


def lr_factor(step: int, warmup: int, total: int | None, schedule: str, final_ratio: float) -> float:
    """Multiplier of the base learning rate at optimiser step ``step`` (0-based): linear warm-up over
    ``warmup`` steps, then constant or a half cosine from 1 to ``final_ratio`` at step ``total``."""
    import math

    if warmup > 0 and step < warmup:
        return (step + 1) / warmup
    if schedule == "constant":
        return 1.0
    progress = min(1.0, max(0, step - warmup) / max(1, (total or 0) - warmup))
    return final_ratio + (1 - final_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def batch_to(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def slice_batch(batch: dict, count: int) -> dict:
    """The first ``count`` scenes of a collated batch."""
    return {k: v[:count] for k, v in batch.items()}


#: The defaults of SceneDiffusion's arguments (one source: :class:`~spread.model.config.SceneDiffusionConfig`).
ARGS = SceneDiffusionConfig
#: torch.compile's modes for ``model.compile_mode``.
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


#: Dynamo's recompile limit while a step is compiled per bucket of object counts (its default, 8, is the buckets of
#: rooms up to 64 objects at ``compile_bucket=8``; a full batch and an epoch's short last one are two graphs a bucket).
COMPILE_RECOMPILE_LIMIT = 64


def compiled_step(fn, mode: str):
    """``fn`` compiled as one graph (``fullgraph``) per input shape, each static (``dynamic=False``: Dynamo's
    automatic dynamic shapes would turn the second object count into one dynamic-shape graph, minutes to compile at
    paper size and slower to run); the process's recompile limit raised to :data:`COMPILE_RECOMPILE_LIMIT`. einops'
    backends for tensors and parameters are registered first: Dynamo guards on the size of einops' registry, which
    its first trace grows by one (a parameter), and the second step would compile the same graph again."""
    import einops
    import torch._dynamo

    for kind in (torch.zeros(1, 1), torch.nn.Parameter(torch.zeros(1, 1))):
        einops.rearrange(kind, "a b -> b a")
    config = torch._dynamo.config
    name = "recompile_limit" if hasattr(config, "recompile_limit") else "cache_size_limit"
    setattr(config, name, max(getattr(config, name), COMPILE_RECOMPILE_LIMIT))
    return torch.compile(fn, mode=mode, fullgraph=True, dynamic=False)


def check_optimisation(lr, weight_decay, graph_dropout, lr_warmup_steps, lr_final_ratio) -> None:
    """The optimiser's and the schedule's hyperparameters, refused by key (``ValueError``) outside their range:
    ``model.lr=inf`` (or ``weight_decay=inf``) trained to NaN weights and exited 0, ``graph_dropout=1.5`` and
    ``lr_warmup_steps=-3`` were taken, ``lr=nan`` was refused by torch naming no key."""
    from spread.checks import whole_number

    def number(value) -> bool:
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

    for key, value, ok, expected in (
            ("lr", lr, lambda v: v > 0, "a finite number > 0"),
            ("weight_decay", weight_decay, lambda v: v >= 0, "a finite number >= 0"),
            ("graph_dropout", graph_dropout, lambda v: 0 <= v <= 1, "a share in [0, 1]"),
            ("lr_final_ratio", lr_final_ratio, lambda v: 0 <= v <= 1, "a share of model.lr in [0, 1]")):
        if not (number(value) and ok(value)):
            raise ValueError(f"model.{key}={value!r}: expected {expected}")
    whole_number(lr_warmup_steps, "model.lr_warmup_steps", 0)


class SceneDiffusion(L.LightningModule):
    """Trains, validates and samples one variant (module docstring); arguments: :class:`SceneDiffusionConfig`
    (``config`` None: the paper's network)."""

    def __init__(self, variant: str = ARGS.variant, config: dict | ModelConfig | None = None,
                 bounds: Sequence[float] | None = None, beta_schedule: str = ARGS.beta_schedule,
                 diffusion_steps: int = ARGS.diffusion_steps, lr: float = ARGS.lr, weight_decay: float = ARGS.weight_decay,
                 ema_decay: float = ARGS.ema_decay, graph_dropout: float = ARGS.graph_dropout,
                 sample_every_n_epochs: int = ARGS.sample_every_n_epochs, val_sampler: str | dict = ARGS.val_sampler,
                 val_sample_scenes: int = ARGS.val_sample_scenes, seed: int = ARGS.seed,
                 prediction: str = ARGS.prediction, loss_weighting: str = ARGS.loss_weighting,
                 min_snr_gamma: float = ARGS.min_snr_gamma, lr_warmup_steps: int = ARGS.lr_warmup_steps,
                 lr_schedule: str = ARGS.lr_schedule, lr_final_ratio: float = ARGS.lr_final_ratio,
                 init_from: str | None = ARGS.init_from, compile: bool = ARGS.compile,
                 compile_mode: str = ARGS.compile_mode, compile_bucket: int = ARGS.compile_bucket,
                 penetration_weight: float = ARGS.penetration_weight,
                 support_weight: float = ARGS.support_weight, support_quantile: float = ARGS.support_quantile,
                 spatial_weight: float = ARGS.spatial_weight, parts_weight: float = ARGS.parts_weight,
                 support_gap_weight: float | None = None):
        super().__init__()
        if support_gap_weight:  # retired (2026-11-27): checkpoints trained before still load and sample
            warnings.warn(f"support_gap_weight={support_gap_weight} is retired: that term (a supported object's box gap) "
                          "no longer exists; sampling is unaffected, further training uses model.support_weight instead",
                          stacklevel=2)
        cfg = ModelConfig.from_any(config)
        sampler = Sampler.from_config(val_sampler)
        check_schedule(beta_schedule, diffusion_steps)  # before anything is made of them
        check_prediction(prediction)
        loss_weights(loss_weighting, prediction, torch.tensor([0.5]), min_snr_gamma)  # validates the name
        check_optimisation(lr, weight_decay, graph_dropout, lr_warmup_steps, lr_final_ratio)
        for key, value in (("penetration_weight", penetration_weight), ("support_weight", support_weight),
                           ("spatial_weight", spatial_weight), ("parts_weight", parts_weight)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"model.{key} must be a finite number >= 0, got {value}")
        if not 0 < support_quantile < 1:
            raise ValueError(f"model.support_quantile must be in (0, 1), got {support_quantile}")
        if compile_mode not in COMPILE_MODES:
            raise ValueError(f"model.compile_mode must be one of {COMPILE_MODES}, got '{compile_mode}'")
        if compile and variant == "geometry" and cfg.nearest in UNCOMPILABLE:
            raise ValueError(f"model.compile=true cannot compile model.config.nearest={cfg.nearest} (the tree search "
                             "runs on the host, the pruned one's blocks have data-dependent sizes): use nearest=auto "
                             "or dense")
        if compile and variant == "geometry" and getattr(cfg, "geometry_distance", "chamfer") == "parts":
            raise ValueError("model.compile=true cannot compile model.config.geometry_distance=parts (it finds the "
                             "parts near each point with a nonzero and branches on its result every step: "
                             "data-dependent sizes): use geometry_distance=chamfer or model.compile=false")
        if isinstance(compile_bucket, bool) or not isinstance(compile_bucket, int) or compile_bucket < 1:
            raise ValueError(f"model.compile_bucket must be an integer >= 1 (objects), got {compile_bucket!r}")
        if lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"unknown lr_schedule '{lr_schedule}' (choose from {LR_SCHEDULES})")
        self.save_hyperparameters({
            "variant": variant, "config": cfg.to_dict(),
            "bounds": None if bounds is None else [float(b) for b in bounds],
            "beta_schedule": beta_schedule, "diffusion_steps": int(diffusion_steps), "lr": lr, "weight_decay": weight_decay, "ema_decay": ema_decay, "graph_dropout": graph_dropout,
            "sample_every_n_epochs": sample_every_n_epochs,
            "val_sampler": dataclasses.asdict(sampler),
            "val_sample_scenes": val_sample_scenes, "seed": seed, "prediction": prediction,
            "loss_weighting": loss_weighting, "min_snr_gamma": float(min_snr_gamma),
            "lr_warmup_steps": int(lr_warmup_steps), "lr_schedule": lr_schedule, "lr_final_ratio": float(lr_final_ratio),
            "init_from": None if init_from is None else str(init_from), "compile": bool(compile),
            "compile_mode": str(compile_mode), "compile_bucket": int(compile_bucket),
            "penetration_weight": float(penetration_weight), "support_weight": float(support_weight),
            "support_quantile": float(support_quantile), "spatial_weight": float(spatial_weight),
            "parts_weight": float(parts_weight),
        })
        self.variant, self.config, self.val_sampler = variant, cfg, sampler
        self.network = SceneDenoiser(cfg, variant, bounds)
        self.ema = EMA(self.network, ema_decay)
        self.noise_schedule = training_scheduler(beta_schedule=beta_schedule, num_train_timesteps=int(diffusion_steps))
        # ᾱ_t (T,) float32 (the scheduler's values), moved with the module: the training step reads it on the device
        # (diffusers' add_noise moves its own copy to the device by assigning an attribute, which a CUDA-graph'd
        # step must not do); not in the state dict
        self.register_buffer("alphas_cumprod", self.noise_schedule.alphas_cumprod.clone(), persistent=False)

    @classmethod
    def from_checkpoint(cls, checkpoint: dict, map_location="cpu") -> "SceneDiffusion":
        """The model of a checkpoint's dict (read with :func:`spread.safe_load.load_checkpoint`, which runs no
        code): its hyperparameters, then its weights (EMA included), strictly."""
        model = cls(**checkpoint["hyper_parameters"])
        model.load_state_dict(checkpoint["state_dict"])
        return model.to(map_location)

    # ---- bounds -------------------------------------------------------------------------------------
    def set_bounds(self, bounds: Sequence[float]) -> None:
        self.network.set_bounds(bounds)
        self.ema.module.set_bounds(bounds)
        self.hparams["bounds"] = [float(b) for b in bounds]

    def setup(self, stage: str | None = None) -> None:
        if self._trainer is None:
            return
        if stage in (None, "fit") and self.hparams.init_from and not getattr(self, "_initialised", False):
            self.initialise_from(self.hparams.init_from)
        if torch.isfinite(self.network.bounds).all():
            return
        datamodule = self.trainer.datamodule
        if datamodule is not None and hasattr(datamodule, "translation_bounds"):
            self.set_bounds(datamodule.translation_bounds())  # what its datasets normalise with (augmented or not)
            return
        root = getattr(datamodule, "root", None) if datamodule is not None else None
        if root is None:
            if self.variant == "geometry":
                raise RuntimeError("SceneDiffusion: pass bounds= or train with a SceneDataModule (its stats.json)")
            return
        from spread.data.stats import load_stats

        self.set_bounds(load_stats(root / "stats.json")["bounds_translations"])

    def data_hparams(self, datamodule) -> dict:
        """The hyperparameters :meth:`setup` takes from ``datamodule``'s data when fitting starts: ``bounds``, as its
        datasets normalise with them (:meth:`~spread.data.SceneDataModule.translation_bounds`; {} otherwise)."""
        bounds = getattr(datamodule, "translation_bounds", None)
        return {} if bounds is None else {"bounds": [float(b) for b in bounds()]}

    def initialise_from(self, path: str) -> list[str]:
        """Start the network (and its EMA) from the EMA weights of checkpoint ``path``: every weight of the
        same name and shape; the rest (a ``geometry`` model's perceiver and geometry attention, starting from a
        ``base`` one) keeps its fresh initialisation, with each geometry attention's output at zero so the
        model predicts at step 0 what the checkpoint's did. Translation bounds come from the data, not the
        checkpoint. Returns the names left fresh."""
        from pathlib import Path

        file = Path(path)
        if not file.is_file():
            raise FileNotFoundError(f"model.init_from={path}: no such checkpoint file")
        from spread.safe_load import expect_checkpoint

        state = expect_checkpoint(file, "model.init_from", method="spread").get("state_dict", {})
        prefix = "ema.module."
        source = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix) and not k.endswith("bounds")}
        source = upgrade_state_dict(self.network, source)  # a checkpoint of an older layout, in today's names
        if not source:
            raise ValueError(f"model.init_from={path}: no EMA weights ('{prefix}*') in its state_dict")
        own = self.network.state_dict()
        for name, value in source.items():
            if name in own and own[name].shape != value.shape:
                raise ValueError(f"model.init_from={path}: weight '{name}' has shape {tuple(value.shape)}, "
                                 f"this model's {tuple(own[name].shape)} (another network size?)")
        loaded = {k: v for k, v in source.items() if k in own}
        fresh = sorted(k for k in own if k not in loaded and not k.endswith("bounds"))
        self.network.load_state_dict({**own, **loaded})
        with torch.no_grad():
            for i, block in enumerate(self.network.denoiser.blocks):
                out = getattr(block.geometry_attn, "to_out", None)
                if out is not None and f"denoiser.blocks.{i}.geometry_attn.to_out.0.weight" in fresh:
                    out[0].weight.zero_()
                    out[0].bias.zero_()
        self.ema.module.load_state_dict(self.network.state_dict())
        self.ema.num_updates.zero_()
        self._initialised = True
        return fresh

    # ---- training -------------------------------------------------------------------------------------
    def alpha_bar(self, timesteps: torch.Tensor) -> torch.Tensor:
        """ᾱ_t (B,) float64 of the training schedule at integer timesteps (B,)."""
        alphas = self.alphas_cumprod.to(device=timesteps.device, dtype=torch.float64)
        return alphas[timesteps.long()]

    def add_noise(self, x0: torch.Tensor, noise: torch.Tensor, timesteps: torch.Tensor) -> torch.Tensor:
        """x_t = √ᾱ_t · x0 + √(1 − ᾱ_t) · ε for states x0, noise (B, N, C) at integer timesteps (B,): diffusers'
        ``DDPMScheduler.add_noise`` to the bit, from the module's ᾱ buffer (no attribute assigned: capturable)."""
        alphas = self.alphas_cumprod.to(dtype=x0.dtype)[timesteps.to(x0.device)]
        return (alphas ** 0.5)[:, None, None] * x0 + ((1 - alphas) ** 0.5)[:, None, None] * noise

    def training_terms(self, batch: dict, noise: torch.Tensor | None = None, timesteps: torch.Tensor | None = None,
                       network: SceneDenoiser | None = None, pose_terms: bool = True) -> dict[str, torch.Tensor]:
        """The loss's terms on one batch: ``mse``, the weighted MSE of the ``prediction``, and (when
        ``pose_terms`` is true) those of :meth:`term_weights` that are on: ``penetration``, the ᾱ_t-weighted box
        overlap of the decoded x̂_0 beyond the training scene's, ``support``, its support pairs' rest height and
        overhang error (metres, :mod:`spread.model.penetration`); ``noise`` (B, N, 9) and ``timesteps`` (B,)
        are drawn when not given."""
        network = network if network is not None else self.network
        x0, mask = batch["x"].float(), batch["mask"].bool()
        B = x0.shape[0]
        keep = mask[..., None].to(x0.dtype)
        noise = (torch.randn_like(x0) if noise is None else noise.to(x0)) * keep
        if timesteps is None:
            timesteps = torch.randint(0, self.noise_schedule.config.num_train_timesteps, (B,), device=x0.device)
        timesteps = timesteps.to(x0.device).long()
        x_t = self.add_noise(x0, noise, timesteps) * keep
        drop = None
        if network.training and self.hparams.graph_dropout > 0:
            drop = torch.rand(B, device=x0.device) < self.hparams.graph_dropout
        output = self.network_output(network, x_t, timesteps, network.condition(batch, drop))
        prediction = self.hparams.get("prediction", "epsilon")
        alpha_bar = self.alpha_bar(timesteps)
        target = prediction_target(prediction, x0, noise, alpha_bar) * keep
        weights = None
        if self.hparams.get("loss_weighting", "none") != "none":
            weights = loss_weights(self.hparams.loss_weighting, prediction, alpha_bar, self.hparams.min_snr_gamma)
        terms = {"mse": masked_mse(output, target, mask, weights)}
        extra = self.term_weights() if pose_terms else {}
        if extra:
            x0_hat = x0_from_prediction(prediction, output, x_t, alpha_bar)
            bounds = network.bounds
            if not torch.isfinite(bounds).all():
                raise RuntimeError(f"model.{next(iter(extra))}_weight needs the translation bounds "
                                   "(train with a SceneDataModule)")
            translation, rotation = poses_from_state(x0_hat, bounds)
            with torch.no_grad():
                true_translation, true_rotation = poses_from_state(x0, bounds)
            poses = (translation, rotation, true_translation, true_rotation, batch["extents"].to(x0), mask)
            per_scene = {}
            if "penetration" in extra:
                per_scene["penetration"] = penetration_excess(*poses)
            if "support" in extra:
                per_scene["support"] = support_error(*poses, batch["physical"] == PHYSICAL_SUPPORT,
                                                     float(self.hparams.get("support_quantile", 0.5)))
            if "spatial" in extra:
                per_scene["spatial"] = spatial_excess(*poses, batch["spatial"])
            if "parts" in extra:
                per_scene["parts"] = parts_excess(PartPlanes.from_batch(batch, mask), batch["points"], *poses[:4], mask)
            for name, value in per_scene.items():
                terms[name] = (value * alpha_bar.to(value)).mean()
        return terms

    def term_weights(self) -> dict[str, float]:
        """The weights of the loss's terms beside the MSE that are on: ``penetration`` (λ), ``support`` (μ),
        ``spatial`` (ν) and ``parts`` (the convex parts' penetration, :mod:`spread.model.parts_term`)."""
        weights = {"penetration": float(self.hparams.get("penetration_weight", 0.0)),
                   "support": float(self.hparams.get("support_weight", 0.0)),
                   "spatial": float(self.hparams.get("spatial_weight", 0.0)),
                   "parts": float(self.hparams.get("parts_weight", 0.0))}
        return {name: w for name, w in weights.items() if w > 0}

    def combine(self, terms: dict[str, torch.Tensor]) -> torch.Tensor:
        """The loss from :meth:`training_terms`: the MSE plus each other term times its weight."""
        weights = self.term_weights()
        loss = terms["mse"]
        for name, value in terms.items():
            if name != "mse":
                loss = loss + weights[name] * value
        return loss

    def training_loss(self, batch: dict, noise: torch.Tensor | None = None, timesteps: torch.Tensor | None = None,
                      network: SceneDenoiser | None = None, pose_terms: bool = True) -> torch.Tensor:
        """The training loss on one batch: the weighted MSE of the ``prediction`` plus ``penetration_weight`` ×
        the penetration term and ``support_weight`` × the support term (:meth:`training_terms`)."""
        return self.combine(self.training_terms(batch, noise, timesteps, network, pose_terms))

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        size = batch["x"].shape[0]
        if self.hparams.get("compile", False):
            mode = self.hparams.get("compile_mode", "default")
            if getattr(self, "_compiled_loss", None) is None:
                self._compiled_loss = compiled_step(self.training_loss, mode)
            bucket = self.hparams.get("compile_bucket", ARGS.compile_bucket)
            batch = pad_objects(batch, round_up(batch["x"].shape[1], bucket))  # one graph per bucket of counts
            if mode == "reduce-overhead":  # a new step: the graphs' outputs of the last one may be overwritten
                torch.compiler.cudagraph_mark_step_begin()
                loss = self._compiled_loss(batch).clone()  # logged after the next replay: not the graph's buffer
            else:
                loss = self._compiled_loss(batch)
        else:
            terms = self.training_terms(batch)
            loss = self.combine(terms)
            if len(terms) > 1:
                for name, value in terms.items():
                    self.log(f"train/{name}", value, batch_size=size)
        self.log("train/loss", loss, batch_size=size, prog_bar=True)
        return loss

    def optimizer_step(self, *args, **kwargs) -> None:
        """The optimiser's step, then the EMA's (once per real step, gradient accumulation included). A CUDA-graph'd
        step's gradients live in the graphs' memory, which the next replay overwrites: they are dropped once used
        (Lightning drops them before the next step anyway; a model moved or saved after the last step would read
        overwritten memory)."""
        super().optimizer_step(*args, **kwargs)
        self.ema.update(self.network)
        if self.hparams.get("compile", False) and self.hparams.get("compile_mode", "default") == "reduce-overhead":
            self.zero_grad(set_to_none=True)

    def epsilon(self, output: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """ε̂ from the network's raw output at states x_t and timesteps t (B,) (the identity for ε-prediction)."""
        prediction = self.hparams.get("prediction", "epsilon")
        if prediction == "epsilon":
            return output
        return epsilon_from_prediction(prediction, output, x_t, self.alpha_bar(t.to(x_t.device)))

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, batch: dict) -> torch.Tensor:
        """ε̂ (B, N, 9) of the training network for states x_t (B, N, 9) at timesteps t (B,)."""
        return self.epsilon(self.network_output(self.network, x_t, t, self.network.condition(batch)), x_t, t)

    def network_output(self, network: SceneDenoiser, x_t: torch.Tensor, t: torch.Tensor, cond,
                       geometry_scale: float = 1.0) -> torch.Tensor:
        """The network's raw output at states x_t (B, N, 9) and timesteps t (B,). With ``model.config.geometry_at=
        x0_hat`` (self-conditioned geometry) its geometry features pose the scene at its own clean estimate: a
        first pass at x_t, without gradients, gives x̂_0 (clipped to the states' ±1 box, zero at padding), and the
        second pass — the one returned — reads the geometry there. The same in training and at every sampling step.

        ``geometry_scale`` s ≠ 1 (sampling; a +Geometry model): classifier-free guidance on the geometry features,
        o_blind + s (o − o_blind), where o_blind is the same pass reading a scene with nothing near anything
        (``blind``: :func:`~spread.model.geometry.blind_distances`). ε̂ is affine in the output at fixed x_t and t
        with weights summing to 1, so this is the same mix of ε̂ (whatever ``prediction`` is); one pass more."""
        pose = None
        if network.perceiver is not None and getattr(network.config, "geometry_at", "x_t") != "x_t":
            with torch.no_grad():
                first = network(x_t, t, cond)
                alpha_bar = self.alpha_bar(t.to(x_t.device).long())
                x0_hat = x0_from_prediction(self.hparams.get("prediction", "epsilon"), first, x_t, alpha_bar)
                pose = x0_hat.clamp(-1.0, 1.0) * cond.mask[..., None].to(x_t.dtype)
        out = network(x_t, t, cond, pose=pose)
        if geometry_scale == 1.0:
            return out
        blind = network(x_t, t, cond, pose=pose, blind=True)
        return blind + geometry_scale * (out - blind)

    def configure_optimizers(self):
        optimizer = torch.optim.AdamW(self.network.parameters(), lr=self.hparams.lr,
                                      weight_decay=self.hparams.weight_decay)
        warmup, schedule = int(self.hparams.get("lr_warmup_steps", 0)), self.hparams.get("lr_schedule", "constant")
        if warmup <= 0 and schedule == "constant":
            return optimizer
        total = None
        if schedule == "cosine":
            total = int(self.trainer.max_steps) if self._trainer is not None else -1
            if total is None or total <= 0:
                raise ValueError("model.lr_schedule=cosine decays to trainer.max_steps: set trainer.max_steps")
        final = float(self.hparams.get("lr_final_ratio", 0.1))
        scheduler = torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda step: lr_factor(step, warmup, total, schedule, final))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    # ---- validation -----------------------------------------------------------------------------------
    def _sampling_due(self) -> bool:
        k = int(self.hparams.sample_every_n_epochs)
        return k > 0 and not self.trainer.sanity_checking and (self.current_epoch + 1) % k == 0

    def validation_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        x0 = batch["x"]
        B = x0.shape[0]
        gen = torch.Generator().manual_seed(int(self.hparams.seed) * 1_000_003 + batch_idx)
        noise = torch.randn(x0.shape, generator=gen).to(x0)
        timesteps = torch.randint(0, self.noise_schedule.config.num_train_timesteps, (B,), generator=gen)
        # the denoising MSE alone: val/loss compares across runs with and without the pose terms
        loss = self.training_loss(batch, noise, timesteps, network=self.ema.module, pose_terms=False)
        self.log("val/loss", loss, batch_size=B, sync_dist=True, prog_bar=True)
        if batch_idx == 0 and self._sampling_due():
            scenes = slice_batch(batch, int(self.hparams.val_sample_scenes))
            gen = torch.Generator().manual_seed(int(self.hparams.seed))
            poses = self.sample(scenes, self.val_sampler, generator=gen)
            correct, pairs = graph_recall(poses.translation, poses.rotation, scenes["points"], scenes["spatial"],
                                          scenes["mask"])
            self.log("val/grecall", correct.sum().float() / pairs.sum().clamp(min=1), batch_size=len(pairs),
                     sync_dist=True)
        return loss

    # ---- sampling -------------------------------------------------------------------------------------
    def denoiser(self, batch: dict, use_ema: bool = True, graph_scale: float = 1.0, geometry_scale: float = 1.0):
        """(ε-function, mask) for the batch's scenes: ``eps_fn(x_t (B, N, 9), t (B,)) → ε̂`` of the EMA (or
        training) network conditioned on the batch's graphs and assets; ``graph_scale ≠ 1`` mixes in the
        graph-free prediction (ε̂ = ε̂_∅ + s (ε̂_G − ε̂_∅), classifier-free guidance); ``geometry_scale ≠ 1`` (a
        +Geometry model) does the same with the geometry-blind prediction inside each branch
        (:meth:`network_output`). The network is used as it is (call ``eval()`` first, as :meth:`sample_states`
        and the sampling pipeline do)."""
        network = self.ema.module if use_ema else self.network
        geometry_scale = float(geometry_scale)
        if geometry_scale != 1.0 and not self.has_geometry:
            raise ValueError(f"geometry_scale={geometry_scale}: a model without geometry features (model.variant="
                             "base) has no geometry to guide; sample it with geometry_scale=1")
        batch = batch_to(batch, self.device)
        cond = network.condition(batch)
        null = network.null_condition(cond) if graph_scale != 1.0 else None

        def eps_fn(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            if null is None:
                return self.epsilon(self.network_output(network, x_t, t, cond, geometry_scale), x_t, t)
            with sharing_geometry(cond):  # both branches read the scene posed at x_t: its geometry made once
                eps = self.epsilon(self.network_output(network, x_t, t, cond, geometry_scale), x_t, t)
                eps_null = self.epsilon(self.network_output(network, x_t, t, null, geometry_scale), x_t, t)
            return eps_null + graph_scale * (eps - eps_null)

        return eps_fn, cond.mask

    def denoising(self, batch: dict, use_ema: bool = True, graph_scale: float = 1.0,
                  geometry_scale: float = 1.0) -> Denoising:
        """The batch's :class:`~spread.model.diffusion.Denoising` for the one sampling loop: :meth:`denoiser`'s
        ε-function and mask, 9-d states on the model's training schedule, decoded by :meth:`decode`."""
        eps_fn, mask = self.denoiser(batch, use_ema, graph_scale, geometry_scale)
        return Denoising(eps_fn, mask, lambda x: self.decode(x, mask), 9, self.noise_schedule.config)

    @property
    def has_geometry(self) -> bool:
        """Whether the network reads geometry features (a +Geometry model): only then may sampling guide them
        (``geometry_scale``, :meth:`denoiser`)."""
        return self.network.perceiver is not None

    @property
    def cuda_graph_capturable(self) -> bool:
        """Whether a sampling step on CUDA reads nothing on the host, so ``sampling.cuda_graph`` can record it (and
        does by default): base always; +Geometry with the release's chamfer feature searched by ``dense`` (``auto`` on
        CUDA) where its Triton kernel runs (:func:`~spread.model.nearest_dense.graph_safe`). The ``tree`` and
        ``pruned`` searches (host work, data-dependent block sizes), ``dense``'s torch fallback on a CUDA device without
        the kernel and the ``parts`` distance (one ``nonzero`` a step) read the host every step."""
        from spread.model.nearest_dense import graph_safe

        config = self.network.config
        if not self.has_geometry:
            return True
        return (getattr(config, "geometry_distance", "chamfer") == "chamfer"
                and getattr(config, "nearest", "auto") not in UNCOMPILABLE and graph_safe(self.device))

    @property
    def bounds(self) -> torch.Tensor:
        """(6,) translation bounds [min xyz, max xyz], metres: the normalisation of a state's translation."""
        return self.network.bounds

    def decode(self, x: torch.Tensor, mask: torch.Tensor) -> Poses:
        """Normalised states x (B, N, 9) → :class:`Poses` (metres, world-from-local; 0 / identity at padding)."""
        mask = mask.to(x.device).bool()
        translation, rotation = poses_from_state(x, self.network.bounds)
        eye = torch.eye(3, device=x.device, dtype=rotation.dtype).expand_as(rotation)
        return Poses(torch.where(mask[..., None], translation, 0.0), torch.where(mask[..., None, None], rotation, eye))

    @torch.no_grad()
    def sample_states(self, batch: dict, sampler: Sampler | str | dict | None = None,
                      generator: torch.Generator | list[torch.Generator] | None = None, x0_hook: Hook | None = None,
                      sample_hook: Hook | None = None, use_ema: bool = True, graph_scale: float = 1.0) -> torch.Tensor:
        """Normalised states x̂_0 (B, N, 9) for the batch's scenes (graphs, assets, mask); zero at padding.
        Unguided unless hooks are given (validation, quick looks); guided sampling with the platform's guidance
        is :class:`spread.sampling.ScenePipeline` (the same loop, :func:`~spread.model.diffusion.denoise`)."""
        network = self.ema.module if use_ema else self.network
        was_training = network.training
        network.eval()
        try:
            return denoise(self.denoising(batch, use_ema, graph_scale), sampler, generator,
                           [SamplingCallback(x0_hook=x0_hook, sample_hook=sample_hook)])
        finally:
            network.train(was_training)

    def sample(self, batch: dict, sampler: Sampler | str | dict | None = None,
               generator: torch.Generator | list[torch.Generator] | None = None, x0_hook: Hook | None = None,
               sample_hook: Hook | None = None, use_ema: bool = True, graph_scale: float = 1.0) -> Poses:
        """Sample poses for the batch's scenes: translation (B, N, 3) metres, rotation (B, N, 3, 3)."""
        x = self.sample_states(batch, sampler, generator, x0_hook, sample_hook, use_ema, graph_scale)
        return self.decode(x, batch["mask"])
