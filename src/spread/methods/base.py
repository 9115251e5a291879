"""``BaselineModule``: what ATISS, DiffuScene and InstructScene share as LightningModules on the platform.

* Data: the same :class:`~spread.data.SceneDataModule` batches as SceneDiffusion, read through
  :func:`spread.methods.boxes.objects_of` (class, box, heading, rest orientation).
* Dataset facts, filled at ``setup`` from the trainer's data module when not given and saved in the
  checkpoint's hyperparameters: ``bounds`` (stats.json translation bounds), ``categories`` (the dataset's
  category list: the class vocabulary) and ``size_bounds`` (smallest and largest asset extent, metres).
  The network is built once they are known (``__init__`` when loading a checkpoint, else ``setup``).
* Optimiser: each method's own (``optimizer`` adam / adamw, ``lr``, ``weight_decay``; a subclass may add a
  step decay, hyperparameters ``lr_step`` steps and ``lr_decay``); gradient clipping is the trainer's. EMA (:class:`spread.model.ema.EMA`) with the method's decay (0 = the plain weights, for the
  methods that use none); validation and sampling use it by default.
* ``val/loss``: the method's training loss with seeded randomness (comparable across epochs).
* :meth:`sample` has SceneDiffusion's signature and returns :class:`spread.model.module.Poses`.

Subclasses set :attr:`method` and :attr:`config_class` and implement ``make_network`` and ``loss``.
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any, Mapping, Sequence

import lightning as L
import torch

from spread.model.ema import EMA


class BaselineConfig:
    """Mixin of the methods' config dataclasses: presets by name and conversion from a checkpoint dict."""

    @classmethod
    def presets(cls) -> dict:
        return {"tiny": cls.tiny, "paper": cls.paper}

    @classmethod
    def from_any(cls, config, **overrides):
        """A preset name ("tiny", "paper"), a mapping of fields (from a checkpoint or Hydra), or a config."""
        if isinstance(config, cls):
            return dataclasses.replace(config, **overrides)
        if isinstance(config, str):
            if config not in cls.presets():
                raise ValueError(f"{cls.__name__}: unknown preset '{config}' (choose from {sorted(cls.presets())})")
            return cls.presets()[config](**overrides)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(config) - known
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown fields {sorted(unknown)}")
        return cls(**{**dict(config), **overrides})

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def dataset_facts(root) -> dict:
    """``bounds``, ``categories`` and ``size_bounds`` of a dataset folder (module docstring)."""
    from pathlib import Path

    from spread.assets.library import AssetLibrary
    from spread.data.dataset import load_manifest_categories
    from spread.data.stats import load_stats

    root = Path(root)
    library = AssetLibrary.load(root / "assets")
    extents = torch.tensor([list(r.extents) for r in library.records.values()], dtype=torch.float64)
    return {"bounds": [float(b) for b in load_stats(root / "stats.json")["bounds_translations"]],
            "categories": load_manifest_categories(root / "manifest.json") or list(library.categories),
            "size_bounds": [float(extents.min()), float(extents.max())]}


class BaselineModule(L.LightningModule):
    method: str = ""
    config_class: type = BaselineConfig

    def __init__(self, config: str | Mapping | Any = "tiny", bounds: Sequence[float] | None = None,
                 categories: Sequence[str] | None = None, size_bounds: Sequence[float] | None = None,
                 lr: float = 1e-4, weight_decay: float = 0.0, optimizer: str = "adam", ema_decay: float = 0.0,
                 seed: int = 0, **method_hparams):
        super().__init__()
        given = method_hparams.pop("method", self.method)
        if given != self.method:
            raise ValueError(f"{type(self).__name__}: hyperparameters are for method '{given}', not '{self.method}'")
        cfg = self.config_class.from_any(config)
        if optimizer not in ("adam", "adamw"):
            raise ValueError(f"{self.method}: optimizer must be 'adam' or 'adamw', got {optimizer!r}")
        self.save_hyperparameters({
            "method": self.method, "config": cfg.to_dict(),
            "bounds": None if bounds is None else [float(b) for b in bounds],
            "categories": None if categories is None else [str(c) for c in categories],
            "size_bounds": None if size_bounds is None else [float(b) for b in size_bounds],
            "lr": float(lr), "weight_decay": float(weight_decay), "optimizer": optimizer,
            "ema_decay": float(ema_decay), "seed": int(seed), **method_hparams,
        })
        self.config = cfg
        self.network: torch.nn.Module | None = None
        self.ema: EMA | None = None
        if self.ready:
            self.build()

    # ---- dataset facts and lazy construction --------------------------------------------------------
    @property
    def ready(self) -> bool:
        hp = self.hparams
        return hp.bounds is not None and hp.categories is not None and hp.size_bounds is not None

    @property
    def num_classes(self) -> int:
        return len(self.hparams.categories)

    @property
    def bounds(self) -> torch.Tensor:
        return torch.tensor(self.hparams.bounds, dtype=torch.float32, device=self.device)

    def make_network(self) -> torch.nn.Module:
        raise NotImplementedError

    def build(self) -> None:
        self.network = self.make_network()
        self.ema = EMA(self.network, self.hparams.ema_decay)

    def data_hparams(self, datamodule) -> dict:
        """The hyperparameters :meth:`setup` takes from ``datamodule``'s data when fitting starts (those not given:
        ``bounds``, ``categories``, ``size_bounds``), as it would set them now; {} without a data folder."""
        root = getattr(datamodule, "root", None)
        return {} if root is None else dataset_facts(root)

    def setup(self, stage: str | None = None) -> None:
        datamodule = self.trainer.datamodule if self._trainer is not None else None
        root = getattr(datamodule, "root", None)
        if root is None:
            if not self.ready:
                raise RuntimeError(f"{self.method}: pass bounds, categories and size_bounds, or train with a "
                                   f"SceneDataModule (its stats.json, manifest and asset library)")
            return
        facts = dataset_facts(root)
        for key, value in facts.items():
            given = self.hparams[key]
            if given is None:
                self.hparams[key] = value
            elif key == "categories" and list(given) != list(value):
                raise ValueError(f"{self.method}: the checkpoint's categories ({len(given)}) differ from "
                                 f"{root}/manifest.json's ({len(value)}); train a new model for this dataset")
        if self.network is None:
            self.build()

    # ---- training -------------------------------------------------------------------------------------
    def loss(self, batch: dict, network: torch.nn.Module, generator: torch.Generator | None = None) -> dict:
        """{"loss": scalar, other named terms} of one batch; random draws from ``generator`` when given."""
        raise NotImplementedError

    def training_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        terms = self.loss(batch, self.network)
        B = batch["x"].shape[0]
        self.log("train/loss", terms["loss"], batch_size=B, prog_bar=True)
        for name, value in terms.items():
            if name != "loss":
                self.log(f"train/{name}", value, batch_size=B)
        return terms["loss"]

    def validation_step(self, batch: dict, batch_idx: int) -> torch.Tensor:
        gen = torch.Generator().manual_seed(int(self.hparams.seed) * 1_000_003 + batch_idx)
        terms = self.loss(batch, self.ema.module, generator=gen)
        self.log("val/loss", terms["loss"], batch_size=batch["x"].shape[0], sync_dist=True, prog_bar=True)
        return terms["loss"]

    def optimizer_step(self, *args, **kwargs) -> None:
        super().optimizer_step(*args, **kwargs)
        self.ema.update(self.network)

    def configure_optimizers(self):
        kind = torch.optim.AdamW if self.hparams.optimizer == "adamw" else torch.optim.Adam
        optimizer = kind(self.network.parameters(), lr=self.hparams.lr, weight_decay=self.hparams.weight_decay)
        step = int(self.hparams.get("lr_step") or 0)
        if step <= 0:
            return optimizer
        schedule = torch.optim.lr_scheduler.StepLR(optimizer, step_size=step, gamma=float(self.hparams.lr_decay))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}

    # ---- sampling -------------------------------------------------------------------------------------
    def sampling_network(self, use_ema: bool) -> torch.nn.Module:
        if self.network is None:
            raise RuntimeError(f"{self.method}: the network is not built (no dataset facts yet)")
        return self.ema.module if use_ema else self.network

    def sample(self, batch: dict, sampler=None, generator=None, use_ema: bool = True, guidance=None, **kw):
        """Poses (translation (B, N, 3) metres, rotation (B, N, 3, 3)) for the batch's object sets."""
        raise NotImplementedError

    def describe(self) -> str:
        return f"{self.method} {json.dumps(self.config.to_dict())}"


def uniform_draws(generator, shape: tuple[int, ...], device, rows: int = 64) -> torch.Tensor:
    """U(0, 1) draws of ``shape`` = (B, N, K): one generator per scene (a list) draws a fixed (max(N, rows), K)
    block and keeps its first N rows, so a scene's draws do not depend on its batch (as
    :func:`spread.model.diffusion.reverse_process` does for noise); one generator (or None) draws the whole."""
    B, N, K = shape
    if isinstance(generator, (list, tuple)):
        if len(generator) != B:
            raise ValueError(f"{len(generator)} generators for a batch of {B}")
        return torch.stack([torch.rand((max(N, rows), K), generator=g, device=g.device)[:N] for g in generator]).to(device)
    return torch.rand(shape, generator=generator, device=generator.device if generator is not None else device).to(device)
