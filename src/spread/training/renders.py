"""Sampled scenes during training, as images on the run's dashboards (:class:`SampleRenders`).

Every ``every_n_epochs`` epochs, after validation, the first ``scenes`` validation scenes are sampled by the
model (EMA weights, ``sampler``, a fixed seed, so epochs compare) and drawn top-down beside their ground truth
(left: ground truth, right: sampled); the sheet goes to every logger that takes images: MLflow
(``renders/epoch<NNNN>.png`` among the run's artifacts) and wandb (``val/renders``). Rank zero only.
"""

from __future__ import annotations

import lightning as L
import numpy as np
import torch


class SampleRenders(L.Callback):
    """The module docstring's renders; ``every_n_epochs`` ≤ 0 turns them off."""

    def __init__(self, every_n_epochs: int = 10, scenes: int = 2, sampler: str = "ddim-10", seed: int = 0):
        self.every_n_epochs, self.scenes, self.sampler, self.seed = int(every_n_epochs), int(scenes), sampler, seed

    def due(self, trainer) -> bool:
        return (self.every_n_epochs > 0 and not trainer.sanity_checking and trainer.is_global_zero
                and (trainer.current_epoch + 1) % self.every_n_epochs == 0)

    def on_validation_epoch_end(self, trainer, pl_module) -> None:
        from spread.model.module import SceneDiffusion

        if not self.due(trainer) or not isinstance(pl_module, SceneDiffusion) or trainer.datamodule is None:
            return
        sheet = self.sheet(trainer.datamodule.dataset("val"), pl_module)
        if sheet is not None:
            log_image(trainer, sheet, trainer.current_epoch)

    def sheet(self, dataset, module) -> np.ndarray | None:
        """(H, W, 3) uint8: one row per scene, ground truth | sampled (None without validation scenes)."""
        from spread.data.collate import collate_scenes
        from spread.render.sheets import render_grid
        from spread.render.topdown import render_topdown

        n = min(self.scenes, len(dataset))
        if n == 0:
            return None
        batch = collate_scenes([dataset[i] for i in range(n)])
        batch = {k: v.to(module.device) if torch.is_tensor(v) else v for k, v in batch.items()}
        poses = module.sample(batch, self.sampler, generator=torch.Generator().manual_seed(self.seed))
        images = []
        for i in range(n):
            truth = dataset.read(i)
            k = truth.num_objects
            sampled = truth.with_poses(poses.translation[i, :k].cpu().numpy().astype(np.float32),
                                       poses.rotation[i, :k].cpu().numpy().astype(np.float32))
            images += [render_topdown(truth, dataset.library), render_topdown(sampled, dataset.library)]
        return render_grid(images, ncols=2)


def log_image(trainer, image: np.ndarray, epoch: int) -> None:
    """``image`` to the trainer's MLflow and wandb loggers (the CSV logger takes no images)."""
    from lightning.pytorch.loggers import MLFlowLogger, WandbLogger

    for logger in trainer.loggers:
        if isinstance(logger, MLFlowLogger):
            logger.experiment.log_image(logger.run_id, image, artifact_file=f"renders/epoch{epoch:04d}.png")
        elif isinstance(logger, WandbLogger):
            logger.log_image("val/renders", [image], step=trainer.global_step,
                             caption=[f"epoch {epoch}: ground truth | sampled"])
