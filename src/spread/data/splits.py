"""A dataset folder's splits as training asks for them, without torch or Lightning (``spread-train
data.root=<a folder without scenes>`` is refused in half a second, before either loads: docs/robustness.md).

:func:`fit_problem` is the one rule :meth:`spread.data.datamodule.SceneDataModule.check_fit` applies and
:func:`check_fit_config` asks of a training config before anything heavy is imported."""

from __future__ import annotations

import os
from pathlib import Path

#: The platform's data module (``conf/data/scenes.yaml``); another ``data._target_`` is judged by its own code.
SCENE_DATA_MODULE = "spread.data.datamodule.SceneDataModule"


def runs_validation(limit_val_batches) -> bool:
    """Whether a Lightning trainer with this ``limit_val_batches`` (its default 1.0) validates: unless it is 0;
    ``check_val_every_n_epoch: null`` still validates, every ``val_check_interval`` batches across epochs. The one
    rule asked of a trainer (:meth:`SceneDataModule.validates`) and of a trainer's config before it exists
    (:func:`spread.training.fit.trainer_validates`)."""
    return limit_val_batches != 0


def split_files(root: str | os.PathLike, split: str) -> list[Path]:
    """The scene files of ``<root>/<split>`` (none where that folder is not there)."""
    from spread.scene import list_scene_files

    folder = Path(root) / split
    return list_scene_files(folder) if folder.is_dir() else []


def fit_problem(root: str | os.PathLike, validates: bool) -> str | None:
    """Why the dataset folder ``root`` cannot be trained on, in one line, or None: the train split has no scenes,
    its ``stats.json`` or asset index is not there, or the trainer validates (``validates``) and the val split has none (a run that would crash at its first
    validation, with no checkpoint)."""
    root = Path(root)
    if not split_files(root, "train"):
        return f"data.root={root}: no scene files in {root / 'train'} to train on"
    for need, what in (("stats.json", "the normalisation bounds"), ("assets/index.json", "the asset library")):
        if not (root / need).is_file():  # failed when the data was set up, after the run's config was recorded
            return (f"data.root={root}: no {need} ({what}, which spread-generate and spread-import write); "
                    f"give a whole dataset folder")
    if validates and not split_files(root, "val"):
        return (f"data.root={root}: no scene files in {root / 'val'}, and the trainer validates "
                f"(trainer.limit_val_batches is not 0); give a dataset with a val split (spread-generate writes one "
                f"from 10 rooms on) or set trainer.limit_val_batches=0")
    return None


def check_fit_config(cfg) -> None:
    """``ValueError`` (:func:`fit_problem`) for a training config (``spread-train``'s, composed) whose platform data
    module has no scenes to train, or to validate on when its trainer validates; other data modules, and a root
    only the running app can resolve, are left to the data module's own check."""
    from omegaconf import OmegaConf

    try:
        target = OmegaConf.select(cfg, "data._target_", default=None)
        root = OmegaConf.select(cfg, "data.root", default=None)
        limit = OmegaConf.select(cfg, "trainer.limit_val_batches", default=1.0)
    except Exception:  # noqa: BLE001 — an interpolation of the running app's: the data module checks it later
        return
    if target != SCENE_DATA_MODULE or not isinstance(root, str) or not root:
        return
    problem = fit_problem(root, runs_validation(1.0 if limit is None else limit))
    if problem:
        raise ValueError(problem)
