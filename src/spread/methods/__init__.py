"""The methods: SPREAD, the authors' release and the baselines of the paper's Table 1 on the platform's data,
sampler and protocol, their registry (:mod:`~spread.methods.registry`) and how any of their checkpoints is loaded
(:mod:`~spread.methods.loading`).

| method | module | what it is here |
|---|---|---|
| ``atiss`` | :mod:`~spread.methods.atiss` | autoregressive set transformer, DMLL heads, floor-plan token |
| ``diffuscene`` | :mod:`~spread.methods.diffuscene` | DDPM over object slots, 1-D UNet with attention |
| ``physcene`` | :mod:`~spread.methods.diffuscene` | DiffuScene's checkpoint sampled with ``guidance=physcene`` (the guidance term ``box_iou``) |
| ``instructscene`` | :mod:`~spread.methods.instructscene` | graph → layout: graph transformer on a 10-predicate graph |
| ``release`` | :mod:`~spread.methods.release` | the SPREAD release's network with the authors' weights (sampling only; ``spread-release-ckpt out=``) |

Each is a LightningModule that trains on :class:`~spread.data.SceneDataModule` batches
(``spread-train experiment=<method>`` / ``<method>_quick``) and whose ``sample(batch, sampler, generator,
use_ema, **kw)`` returns :class:`~spread.model.module.Poses` like ``SceneDiffusion.sample``; the diffusion ones
give ``denoising(batch)`` and sample through the platform's one loop (:func:`spread.model.diffusion.denoise`), so
``spread-sample`` writes the same scene files and ``spread-evaluate`` scores them unchanged.

**Same object sets.** A baseline predicts poses for the graph's objects: the class, the box size (from
the asset's extents) and the rest orientation are given and held fixed, and each method predicts the box
centre and the heading about y. Where the original method also generates classes and sizes (ATISS,
DiffuScene, InstructScene's layout stage generates sizes), it still models them in training, and at
sampling they are conditioned on (ATISS: the class-conditional ``add_object`` path; the diffusion models:
the known channels are imputed at every step). :mod:`spread.methods.boxes` has the details.

:func:`~spread.methods.loading.load_module` opens any platform checkpoint (these and SceneDiffusion's) by the ``method``
hyperparameter it saved.
"""

from __future__ import annotations

from spread.methods.registry import METHODS, MethodSpec, method_names, method_spec, register_method  # noqa: F401
from spread.methods.loading import (  # noqa: F401
    check_weight_shapes, checkpoint_method, graph_conditioned, load_module, module_class, module_from_checkpoint)


