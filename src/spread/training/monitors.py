"""Training curves besides the loss: the learning rate (Lightning's ``LearningRateMonitor``, ``lr-AdamW``)
and the gradient norm (:class:`GradientNorm`, ``train/grad_norm``), added by :func:`spread.training.fit.train`
whenever a logger is configured, and sampled scenes as images every few epochs (:mod:`spread.training.renders`,
the train config's ``renders``)."""

from __future__ import annotations

import lightning as L
import torch


class GradientNorm(L.Callback):
    """``train/grad_norm``: the global L2 norm of the gradients before each optimizer step (before clipping),
    every ``every_n_steps`` steps (the trainer's ``log_every_n_steps`` by default)."""

    def __init__(self, every_n_steps: int | None = None):
        self.every_n_steps = every_n_steps

    def on_before_optimizer_step(self, trainer, pl_module, optimizer) -> None:
        every = self.every_n_steps or trainer.log_every_n_steps
        if trainer.global_step % max(1, every):
            return
        grads = [p.grad.detach().norm(2) for p in pl_module.parameters() if p.grad is not None]
        if grads:
            pl_module.log("train/grad_norm", torch.stack(grads).norm(2), on_step=True, on_epoch=False)


def monitors(renders: dict | None = None) -> list:
    """The callbacks of the module docstring, and :class:`~spread.training.renders.SampleRenders` with the
    train config's ``renders`` settings (none when absent or ``every_n_epochs`` ≤ 0)."""
    from lightning.pytorch.callbacks import LearningRateMonitor

    from spread.training.renders import SampleRenders

    out = [LearningRateMonitor(logging_interval="step"), GradientNorm()]
    if renders and int(renders.get("every_n_epochs", 0)) > 0:
        out.append(SampleRenders(**dict(renders)))
    return out
