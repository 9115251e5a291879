"""``SceneDataModule``: the dataset folder's train/val/test splits as Lightning dataloaders.

The train loader orders each epoch by (``seed``, epoch) and can resume mid-epoch (:mod:`spread.data.order`),
so the batch order of a run is reproducible, also across a resume; under DDP Lightning's distributed sampler
takes over (seeded likewise per epoch). Items carry no randomness of their own (points are fixed per asset), so
worker count does not change what a batch holds. ``augment=true`` trains on the 8 floor symmetries of every room
(:mod:`spread.data.augment`): each epoch draws ``len(train)`` distinct (room, symmetry) pairs from the
8·``len(train)`` in the same (seed, epoch) order, and every split is normalised with the square bounds
(:meth:`SceneDataModule.translation_bounds`, which the model reads at setup), so a checkpoint's bounds fit
rotated rooms too. ``bucket_batches=K`` > 0 batches rooms of similar object count together (the order sorted
within windows of K batches, :class:`~spread.data.order.EpochOrder`; single process only). Validation and test
items are never transformed. Worker processes get the datasets either by fork (copied)
or by pickling (``multiprocessing_context="spawn"``): the dataset then reloads its asset library
lazily in the worker.
"""

from __future__ import annotations

import os
from pathlib import Path

import lightning as L
import torch
from torch.utils.data import DataLoader

from spread.data.collate import collate_scenes
from spread.data.dataset import SceneDataset, check_max_objects
from spread.data.points import DEFAULT_NUM_POINTS
from spread.data.splits import fit_problem, runs_validation, split_files
from spread.data.stats import load_stats

SPLITS = ("train", "val", "test")


def wraps_sampler(trainer) -> bool:
    """Whether Lightning replaces the training loader's sampler with its distributed one: a distributed strategy
    (DDP, Ray's, ...) with ``use_distributed_sampler`` on — also with one process (``torchrun
    --nproc-per-node=1``), where our resumable :class:`~spread.data.order.EpochOrder` would be wrapped and, resumed
    mid-epoch, yield fewer indices than the wrapper counts. Lightning's own test where its connector has it (a
    private attribute), else more than one process."""
    connector = getattr(trainer, "_accelerator_connector", None)
    if connector is not None and hasattr(connector, "is_distributed"):
        return bool(connector.use_distributed_sampler and connector.is_distributed)
    return trainer.world_size > 1


class SymmetricScenes(torch.utils.data.Dataset):
    """A :class:`SceneDataset` seen under its 8 floor symmetries: item i = room i mod n after transform i // n."""

    def __init__(self, dataset: SceneDataset):
        from spread.data.augment import NUM_TRANSFORMS

        self.dataset, self.transforms = dataset, NUM_TRANSFORMS

    def __len__(self) -> int:
        return self.transforms * len(self.dataset)

    def __getitem__(self, index: int) -> dict:
        n = len(self.dataset)
        return self.dataset.item(index % n, index // n)


#: At most this many loader processes for a training process beside a GPU (``data.num_workers=null``).
AUTO_WORKERS = 4


def loader_workers(devices: int = 1, cpus: int | None = None) -> int:
    """Loader processes for each of the ``devices`` training processes of this node beside a GPU
    (``data.num_workers=null``): up to :data:`AUTO_WORKERS`, leaving each process one CPU of its share of ``cpus``
    (default: the CPUs this process may run on — in a Ray worker, those Ray gave it: a Ray Train worker, a sweep's
    trial, an ablation's training task; each of its loaders, training and validation, gets that many)."""
    if cpus is None:
        reserved = ray_cpus()
        if reserved is not None:
            return max(0, min(AUTO_WORKERS, int(reserved) - 1))
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(0, min(AUTO_WORKERS, int(cpus) // max(1, int(devices)) - 1))


def ray_cpus() -> float | None:
    """The CPUs Ray reserved for this process when it is a Ray worker (a task or actor), else None (not under Ray,
    or Ray's driver). Ray is not imported here: only asked when this process already runs it."""
    import sys

    ray = sys.modules.get("ray")
    if ray is None or not ray.is_initialized():
        return None
    try:
        context = ray.get_runtime_context()
        if context.worker.mode != ray.WORKER_MODE:
            return None
        return context.get_assigned_resources().get("CPU")
    except Exception:  # noqa: BLE001 — an older or newer Ray without these: the process's own CPUs
        return None


class SceneDataModule(L.LightningDataModule):
    """Dataloaders over ``<root>/{train,val,test}`` with :func:`collate_scenes` batching."""

    def __init__(self, root: str | os.PathLike, batch_size: int = 8, num_workers: int | None = 0,
                 num_points: int = DEFAULT_NUM_POINTS, seed: int = 0, pin_memory: bool = False,
                 persistent_workers: bool | None = False, multiprocessing_context: str | None = None,
                 augment: bool = False, cache: bool = True, bucket_batches: int = 0,
                 geometry_distance: str = "chamfer", max_objects: int | None = None):
        super().__init__()
        from spread.checks import whole_number

        self.root = Path(root)
        self.batch_size = whole_number(batch_size, "data.batch_size", 1)  # never 3.274 quietly run as 3
        #: ``num_workers=None`` (the config's default, ``null``): the trainer's device decides (:meth:`use_workers`:
        #: none on a CPU trainer, a few beside a GPU); until then none
        self.auto_workers = num_workers is None
        self.num_workers = whole_number(num_workers, "data.num_workers", 0,
                                        null="workers chosen by the trainer's device") or 0
        self.num_points = whole_number(num_points, "data.num_points", 1)
        self.seed = whole_number(seed, "data.seed", 0)
        self.augment = bool(augment)
        self.cache = bool(cache)
        self.bucket_batches = whole_number(bucket_batches, "data.bucket_batches", 0, note="(0: off)")
        self.max_objects = check_max_objects(max_objects)  # rooms of more objects are skipped and named
        self.geometry_distance = str(geometry_distance)  # the model's (ModelConfig.geometry_distance): what it reads
        self.pin_memory = bool(pin_memory)
        self._persistent_setting = persistent_workers  # None: with the workers, when the trainer's device gives some
        self.persistent_workers = bool(persistent_workers) and self.num_workers > 0
        self._context_setting = multiprocessing_context
        self.multiprocessing_context = multiprocessing_context if self.num_workers > 0 else None
        self.save_hyperparameters({"root": str(self.root), "batch_size": self.batch_size,
                                   "num_workers": self.num_workers, "num_points": self.num_points,
                                   "seed": self.seed, "pin_memory": self.pin_memory, "augment": self.augment,
                                   "bucket_batches": self.bucket_batches, "max_objects": self.max_objects})
        self._library = None
        self._datasets: dict[str, SceneDataset] = {}

    def use_workers(self, count: int) -> None:
        """``count`` loader processes for a ``num_workers=None`` module (the trainer's choice; :func:`loader_workers`),
        kept across epochs unless ``persistent_workers`` was set false; an explicit ``num_workers`` is left alone."""
        if not self.auto_workers:
            return
        self.num_workers = max(0, int(count))
        self.persistent_workers = self.num_workers > 0 and self._persistent_setting is not False
        self.multiprocessing_context = self._context_setting if self.num_workers > 0 else None
        self.hparams["num_workers"] = self.num_workers

    @property
    def library(self):
        if self._library is None:
            from spread.assets.library import AssetLibrary

            self._library = AssetLibrary.load(self.root / "assets")
        return self._library

    def translation_bounds(self) -> list[float]:
        """The bounds every split is normalised with: stats.json's, squared in x and z when augmenting."""
        bounds = load_stats(self.root / "stats.json")["bounds_translations"]
        if not self.augment:
            return [float(b) for b in bounds]
        from spread.data.augment import square_bounds

        return square_bounds(bounds)

    def dataset(self, split: str) -> SceneDataset:
        """The split's dataset, built on first use (sharing one asset library)."""
        if split not in self._datasets:
            self._datasets[split] = SceneDataset(self.root, split, library=self.library, num_points=self.num_points,
                                                 seed=self.seed, bounds=self.translation_bounds(), cache=self.cache,
                                                 geometry_distance=self.geometry_distance,
                                                 max_objects=self.max_objects)
        return self._datasets[split]

    def setup(self, stage: str | None = None) -> None:
        wanted = {"fit": ("train", "val") if self.validates() else ("train",), "validate": ("val",),
                  "test": ("test",), "predict": ("test",)}
        for split in wanted.get(stage, SPLITS) if stage else SPLITS:
            if (self.root / split).is_dir():
                self.dataset(split)
        if stage == "fit":
            self.check_fit()

    def validates(self) -> bool:
        """Whether the trainer runs validation (no trainer yet: assumed so); a run that does not never reads the
        val split (``trainer.limit_val_batches=0``: a val split the object limit empties is no reason to refuse)."""
        trainer = self.trainer
        return trainer is None or runs_validation(trainer.limit_val_batches)

    def check_fit(self, validates: bool | None = None) -> None:
        """Before training: the train split has scenes, and so does val when the trainer validates (a run that
        would crash at its first validation, with no checkpoint, is refused up front). ``validates``: whether the
        trainer will (None: ask :meth:`validates`; ``spread-train`` asks its trainer config before any logger
        starts, :func:`spread.training.fit.trainer_validates`)."""
        problem = fit_problem(self.root, self.validates() if validates is None else validates)
        if problem:
            raise ValueError(problem)

    def skipped_files(self) -> dict[str, list[dict]]:
        """split → the scene files its dataset skipped (file, error), for the splits built so far."""
        return {split: ds.skipped for split, ds in self._datasets.items() if ds.skipped}

    def scene_files(self, split: str) -> list:
        return split_files(self.root, split)

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        generator = torch.Generator().manual_seed(self.seed) if shuffle else None
        dataset, sampler = self.dataset(split), None
        if shuffle and self.augment:
            dataset = SymmetricScenes(dataset)
            sampler = torch.utils.data.RandomSampler(dataset, num_samples=len(self.dataset(split)), generator=generator)
            shuffle, generator = False, None
        return DataLoader(
            dataset, batch_size=self.batch_size, shuffle=shuffle, generator=generator, sampler=sampler,
            num_workers=self.num_workers, collate_fn=collate_scenes, pin_memory=self.pin_memory,
            persistent_workers=self.persistent_workers, multiprocessing_context=self.multiprocessing_context,
        )

    def train_dataloader(self) -> DataLoader:
        trainer = self.trainer
        if trainer is not None and wraps_sampler(trainer):  # Lightning puts its distributed sampler in
            if self.bucket_batches:
                import logging

                logging.getLogger("spread.data").warning(
                    "data.bucket_batches=%d is not applied under DDP (world size %d): Lightning's distributed "
                    "sampler orders the batches", self.bucket_batches, trainer.world_size)
            return self._loader("train", shuffle=True)
        from spread.data.order import EpochOrder, StatefulLoader

        rooms = self.dataset("train")
        dataset, per_epoch = rooms, len(rooms)
        if self.augment:  # the 8 floor symmetries of every room; an epoch still has len(train) items
            dataset = SymmetricScenes(rooms)

        def sizes() -> list[int]:  # object count of every item (a symmetry keeps its room's count)
            counts = rooms.sizes()
            return [counts[i % len(counts)] for i in range(len(dataset))]

        return StatefulLoader(
            dataset, batch_size=self.batch_size,
            sampler=EpochOrder(len(dataset), self.seed, self.train_position, per_epoch=per_epoch,
                               sizes=sizes if self.bucket_batches else None, batch_size=self.batch_size,
                               window=self.bucket_batches),
            num_workers=self.num_workers, collate_fn=collate_scenes, pin_memory=self.pin_memory,
            persistent_workers=self.persistent_workers, multiprocessing_context=self.multiprocessing_context)

    def train_position(self) -> tuple[int, int]:
        """(epoch, train items already seen in it), from the trainer's global step (:mod:`spread.data.order`): with
        ``accumulate_grad_batches`` = a, an optimiser step takes a batches, and the epoch's last ones (fewer than a)
        one more step, so an epoch of b batches is ⌈b / a⌉ steps (``global_step × a`` batches drifted past the epochs
        made: the start left fewer batches than one step, and training stalled, exit 0)."""
        from spread.data.order import batches_per_epoch

        trainer = self.trainer
        if trainer is None:
            return 0, 0
        per_epoch = max(1, batches_per_epoch(len(self.dataset("train")), self.batch_size, trainer.limit_train_batches))
        accumulate = max(1, int(trainer.accumulate_grad_batches))
        epoch, steps = divmod(trainer.global_step, -(-per_epoch // accumulate))
        return epoch, steps * accumulate * self.batch_size

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)

    def predict_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)
