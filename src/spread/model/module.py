"""``SceneDiffusion``: the LightningModule that trains, validates and samples one variant.

* Loss: ε-MSE over the 9 channels of the real objects only (padding excluded from numerator and
  denominator), t ~ U{0, …, T−1}, x_t from the model's DDPM training schedule (``beta_schedule``,
  ``diffusion_steps`` = T; the paper's cosine schedule over 1,000 by default, :mod:`spread.model.diffusion`).
* Optimiser: AdamW (lr 1e-4, weight decay 1e-4, paper supplement) on the network's weights.
* EMA of the weights (:class:`~spread.model.ema.EMA`, a submodule: in the checkpoint, restored on
  resume); validation and :meth:`SceneDiffusion.sample` use it by default.
* Classifier-free guidance training: with probability ``graph_dropout`` a scene's two graphs are
  replaced by padding codes; ``sample(..., graph_scale=s)`` then mixes ε̂ = ε̂_∅ + s (ε̂_G − ε̂_∅).
* Validation: ``val/loss`` with seeded noise and timesteps (comparable across epochs); every
  ``sample_every_n_epochs`` epochs (0 = never) the first ``val_sample_scenes`` scenes of the first
  validation batch are sampled with ``val_sampler`` and scored with graph recall (``val/grecall``,
  :mod:`spread.model.recall`).
* ``bounds`` (stats.json ``bounds_translations``) are needed to pose objects; when not given they are
  read at ``setup`` from the trainer's datamodule folder (``<root>/stats.json``) and saved with the
  checkpoint.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple, Sequence

import lightning as L
import torch

from spread.model.config import ModelConfig, SceneDiffusionConfig
from spread.model.diffusion import Hook, Sampler, training_scheduler
from spread.model.ema import EMA
from spread.model.network import SceneDenoiser
from spread.model.poses import poses_from_state
from spread.model.recall import graph_recall


class Poses(NamedTuple):
    """Sampled poses: translation (B, N, 3) metres (0 at padding), rotation (B, N, 3, 3) world-from-local
    (identity at padding)."""

    translation: torch.Tensor
    rotation: torch.Tensor


def masked_mse(prediction: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the real objects' channels; prediction/target (B, N, C), mask (B, N)."""
    keep = mask[..., None].to(prediction.dtype)
    return ((prediction - target) ** 2 * keep).sum() / (keep.sum() * prediction.shape[-1]).clamp(min=1)


def batch_to(batch: dict, device: torch.device) -> dict:
    return {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def slice_batch(batch: dict, count: int) -> dict:
    """The first ``count`` scenes of a collated batch."""
    return {k: v[:count] for k, v in batch.items()}


#: The defaults of SceneDiffusion's arguments (one source: :class:`~spread.model.config.SceneDiffusionConfig`).
ARGS = SceneDiffusionConfig


class SceneDiffusion(L.LightningModule):
    """Trains, validates and samples one variant (module docstring); arguments: :class:`SceneDiffusionConfig`
    (``config`` None: the paper's network)."""

    def __init__(self, variant: str = ARGS.variant, config: dict | ModelConfig | None = None,
                 bounds: Sequence[float] | None = None, beta_schedule: str = ARGS.beta_schedule,
                 diffusion_steps: int = ARGS.diffusion_steps, lr: float = ARGS.lr, weight_decay: float = ARGS.weight_decay,
                 ema_decay: float = ARGS.ema_decay, graph_dropout: float = ARGS.graph_dropout,
                 sample_every_n_epochs: int = ARGS.sample_every_n_epochs, val_sampler: str | dict = ARGS.val_sampler,
                 val_sample_scenes: int = ARGS.val_sample_scenes, seed: int = ARGS.seed):
        super().__init__()
        cfg = ModelConfig.from_any(config)
        sampler = Sampler.from_config(val_sampler)
        self.save_hyperparameters({
            "variant": variant, "config": cfg.to_dict(),
            "bounds": None if bounds is None else [float(b) for b in bounds],
            "beta_schedule": beta_schedule, "diffusion_steps": int(diffusion_steps), "lr": lr, "weight_decay": weight_decay, "ema_decay": ema_decay, "graph_dropout": graph_dropout,
            "sample_every_n_epochs": sample_every_n_epochs,
            "val_sampler": dataclasses.asdict(sampler),
            "val_sample_scenes": val_sample_scenes, "seed": seed,
        })
        self.variant, self.config, self.val_sampler = variant, cfg, sampler
        self.network = SceneDenoiser(cfg, variant, bounds)
        self.ema = EMA(self.network, ema_decay)
        self.noise_schedule = training_scheduler(beta_schedule=beta_schedule, num_train_timesteps=int(diffusion_steps))

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
        if torch.isfinite(self.network.bounds).all() or self._trainer is None:
            return
        root = getattr(self.trainer.datamodule, "root", None) if self.trainer.datamodule is not None else None
        if root is None:
            if self.variant == "geometry":
                raise RuntimeError("SceneDiffusion: pass bounds= or train with a SceneDataModule (its stats.json)")
            return
        from spread.data.stats import load_stats

        self.set_bounds(load_stats(root / "stats.json")["bounds_translations"])

    # ---- training -------------------------------------------------------------------------------------
    def training_loss(self, batch: dict, noise: torch.Tensor | None = None, timesteps: torch.Tensor | None = None,
                      network: SceneDenoiser | None = None) -> torch.Tensor:
        """ε-MSE of one batch; ``noise`` (B, N, 9) and ``timesteps`` (B,) are drawn when not given."""
        network = network if network is not None else self.network
        x0, mask = batch["x"].float(), batch["mask"].bool()
        B = x0.shape[0]
        keep = mask[..., None].to(x0.dtype)
        noise = (torch.randn_like(x0) if noise is None else noise.to(x0)) * keep
        if timesteps is None:
            timesteps = torch.randint(0, self.noise_schedule.config.num_train_timesteps, (B,), device=x0.device)
        timesteps = timesteps.to(x0.device).long()
        x_t = self.noise_schedule.add_noise(x0, noise, timesteps) * keep
        drop = None
        if network.training and self.hparams.graph_dropout > 0:
            drop = torch.rand(B, device=x0.device) < self.hparams.graph_dropout
        eps = network(x_t, timesteps, network.condition(batch, drop))
        return masked_mse(eps, noise, mask)

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        loss = self.training_loss(batch)
        self.log("train/loss", loss, batch_size=batch["x"].shape[0], prog_bar=True)
        return loss

    def optimizer_step(self, *args, **kwargs) -> None:
        """The optimiser's step, then the EMA's (once per real step, gradient accumulation included)."""
        super().optimizer_step(*args, **kwargs)
        self.ema.update(self.network)

    def forward(self, x_t: torch.Tensor, t: torch.Tensor, batch: dict) -> torch.Tensor:
        """ε̂ (B, N, 9) of the training network for states x_t (B, N, 9) at timesteps t (B,)."""
        return self.network(x_t, t, self.network.condition(batch))

    def configure_optimizers(self):
        return torch.optim.AdamW(self.network.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)

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
        loss = self.training_loss(batch, noise, timesteps, network=self.ema.module)
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
    def denoiser(self, batch: dict, use_ema: bool = True, graph_scale: float = 1.0):
        """(ε-function, mask) for the batch's scenes: ``eps_fn(x_t (B, N, 9), t (B,)) → ε̂`` of the EMA (or
        training) network conditioned on the batch's graphs and assets; ``graph_scale ≠ 1`` mixes in the
        graph-free prediction (ε̂ = ε̂_∅ + s (ε̂_G − ε̂_∅), classifier-free guidance). The network is used as
        it is (call ``eval()`` first, as :meth:`sample_states` and the sampling pipeline do)."""
        network = self.ema.module if use_ema else self.network
        batch = batch_to(batch, self.device)
        cond = network.condition(batch)
        null = network.null_condition(cond) if graph_scale != 1.0 else None

        def eps_fn(x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
            eps = network(x_t, t, cond)
            if null is None:
                return eps
            eps_null = network(x_t, t, null)
            return eps_null + graph_scale * (eps - eps_null)

        return eps_fn, cond.mask

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
        Unguided (validation, quick looks); guided sampling with callbacks is :class:`spread.sampling.ScenePipeline`."""
        network = self.ema.module if use_ema else self.network
        was_training = network.training
        network.eval()
        try:
            eps_fn, mask = self.denoiser(batch, use_ema, graph_scale)
            return Sampler.from_config(sampler).sample(eps_fn, mask, generator=generator, x0_hook=x0_hook,
                                                       sample_hook=sample_hook, schedule=self.noise_schedule.config)
        finally:
            network.train(was_training)

    def sample(self, batch: dict, sampler: Sampler | str | dict | None = None,
               generator: torch.Generator | list[torch.Generator] | None = None, x0_hook: Hook | None = None,
               sample_hook: Hook | None = None, use_ema: bool = True, graph_scale: float = 1.0) -> Poses:
        """Sample poses for the batch's scenes: translation (B, N, 3) metres, rotation (B, N, 3, 3)."""
        x = self.sample_states(batch, sampler, generator, x0_hook, sample_hook, use_ema, graph_scale)
        return self.decode(x, batch["mask"])
