"""Baselines of the paper's Table 1 on the platform's data, sampler and protocol (issue 16).

| method | module | what it is here |
|---|---|---|
| ``atiss`` | :mod:`~spread.baselines.atiss` | autoregressive set transformer, DMLL heads, floor-plan token |
| ``diffuscene`` | :mod:`~spread.baselines.diffuscene` | DDPM over object slots, 1-D UNet with attention |
| ``physcene`` | :mod:`~spread.baselines.diffuscene` | DiffuScene sampled with oriented box-IoU collision guidance |
| ``instructscene`` | :mod:`~spread.baselines.instructscene` | graph → layout: graph transformer on a 10-predicate graph |
| ``release`` | :mod:`~spread.model.release_module` | the SPREAD release's network with the authors' weights (sampling only; ``spread-release-ckpt out=``) |

Each is a LightningModule that trains on :class:`~spread.data.SceneDataModule` batches
(``spread-train experiment=<method>`` / ``<method>_quick``) and whose ``sample(batch, sampler, generator,
use_ema, guidance, **kw)`` returns :class:`~spread.model.module.Poses` like ``SceneDiffusion.sample``, so
``spread-sample`` writes the same scene files and ``spread-evaluate`` scores them unchanged.

**Same object sets.** A baseline predicts poses for the graph's objects: the class, the box size (from
the asset's extents) and the rest orientation are given and held fixed, and each method predicts the box
centre and the heading about y. Where the original method also generates classes and sizes (ATISS,
DiffuScene, InstructScene's layout stage generates sizes), it still models them in training, and at
sampling they are conditioned on (ATISS: the class-conditional ``add_object`` path; the diffusion models:
the known channels are imputed at every step). :mod:`spread.baselines.boxes` has the details.

:func:`load_module` opens any platform checkpoint (these and SceneDiffusion's) by the ``method``
hyperparameter it saved.
"""

from __future__ import annotations

import importlib

#: method → "module:Class"
METHODS = {
    "atiss": "spread.baselines.atiss:ATISS",
    "diffuscene": "spread.baselines.diffuscene:DiffuScene",
    "physcene": "spread.baselines.diffuscene:DiffuScene",
    "instructscene": "spread.baselines.instructscene:InstructScene",
    "spread": "spread.model.module:SceneDiffusion",
    "release": "spread.model.release_module:ReleaseDiffusion",  # the authors' weights (spread-release-ckpt out=)
}
#: Methods that condition on the relation graph (GRecall is meaningful for them).
GRAPH_CONDITIONED = ("instructscene", "spread")


def module_class(method: str):
    """The LightningModule class of a method name (see :data:`METHODS`)."""
    if method not in METHODS:
        raise ValueError(f"unknown method '{method}' (choose from {sorted(METHODS)})")
    module, name = METHODS[method].split(":")
    return getattr(importlib.import_module(module), name)


def checkpoint_method(hparams: dict) -> str:
    """The method a checkpoint's hyperparameters belong to (no ``method`` key: SceneDiffusion)."""
    return str(hparams.get("method") or "spread")


def module_from_checkpoint(checkpoint: dict, map_location="cpu"):
    """The LightningModule of a checkpoint's dict (read with :func:`spread.safe_load.load_checkpoint`, which
    runs no code), of the class its hyperparameters name: built from them, then its weights (EMA included),
    strictly."""
    cls = module_class(checkpoint_method(checkpoint.get("hyper_parameters") or {}))
    if hasattr(cls, "from_checkpoint"):
        return cls.from_checkpoint(checkpoint, map_location=map_location)
    model = cls(**checkpoint["hyper_parameters"])
    model.load_state_dict(checkpoint["state_dict"])
    return model.to(map_location)


def load_module(ckpt_path, map_location="cpu"):
    """The LightningModule saved in ``ckpt_path`` (``weights_only`` loading: no code runs from the file)."""
    from spread.safe_load import load_checkpoint

    return module_from_checkpoint(load_checkpoint(ckpt_path), map_location)


def with_box_guidance(ckpt_path, out_path, box_guidance: dict | None = None):
    """A ``physcene`` checkpoint at ``out_path``: the DiffuScene checkpoint ``ckpt_path`` (same weights) whose
    samples are guided PhyScene-style (``box_guidance``: :class:`~spread.baselines.diffuscene.BoxGuidance`
    fields, default PhyScene's). Written atomically; returns the path."""
    import dataclasses
    from pathlib import Path

    import torch

    from spread.baselines.diffuscene import BoxGuidance
    from spread.io import atomic_path

    from spread.safe_load import load_checkpoint

    ckpt = load_checkpoint(ckpt_path)
    hparams = dict(ckpt.get("hyper_parameters") or {})
    if checkpoint_method(hparams) not in ("diffuscene", "physcene"):
        raise ValueError(f"{ckpt_path}: a '{checkpoint_method(hparams)}' checkpoint; box guidance needs DiffuScene")
    guide = BoxGuidance.from_any(box_guidance if box_guidance is not None else {})
    if guide is None:
        raise ValueError(f"box_guidance={box_guidance!r} guides nothing (weight and last_steps must be > 0)")
    hparams.update(method="physcene", box_guidance=dataclasses.asdict(guide))
    ckpt["hyper_parameters"] = hparams
    out_path = Path(out_path)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(out_path) as tmp:
        torch.save(ckpt, tmp)
    return out_path
