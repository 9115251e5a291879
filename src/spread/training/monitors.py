"""Training curves besides the loss: the learning rate (Lightning's ``LearningRateMonitor``, ``lr-AdamW``),
the gradient norm (:class:`GradientNorm`, ``train/grad_norm``) and the throughput (:class:`Throughput`:
``perf/steps_per_s``, ``perf/scenes_per_s``, ``perf/data_wait_share``, ``perf/gpu_mem_GiB``), added by
:func:`spread.training.fit.train` whenever a logger is configured (wandb and MLflow alike), and sampled scenes as
images every few epochs (:mod:`spread.training.renders`, the train config's ``renders``)."""

from __future__ import annotations

import time

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


class Throughput(L.Callback):
    """Every ``every_n_steps`` optimiser steps (the trainer's ``log_every_n_steps`` by default), over those steps:
    ``perf/steps_per_s``, ``perf/scenes_per_s`` (scenes of the batches seen), ``perf/data_wait_share`` (the share of
    the wall time between the end of one training batch and the start of the next — the loader, not the model —
    of the whole) and, on CUDA, ``perf/gpu_mem_GiB`` (the peak allocated since the last report). Wall-clock times on
    the host; reading them synchronises nothing on the device (a step's time includes the device's backlog only
    where the host waits for it anyway)."""

    def __init__(self, every_n_steps: int | None = None):
        self.every_n_steps = every_n_steps
        self._reset(None)

    def _reset(self, now: float | None) -> None:
        self.window_start, self.batch_end, self.waited, self.scenes, self.steps = now, None, 0.0, 0, 0

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        now = time.perf_counter()
        if self.window_start is None:
            self._reset(now)
        elif self.batch_end is not None:
            self.waited += now - self.batch_end

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        now = time.perf_counter()
        self.batch_end = now
        self.steps += 1
        x = batch.get("x") if isinstance(batch, dict) else None
        self.scenes += int(x.shape[0]) if x is not None else 0
        every = max(1, self.every_n_steps or trainer.log_every_n_steps)
        if self.steps < every:
            return
        elapsed = max(now - self.window_start, 1e-9)
        values = {"perf/steps_per_s": self.steps / elapsed, "perf/scenes_per_s": self.scenes / elapsed,
                  "perf/data_wait_share": self.waited / elapsed}
        if torch.cuda.is_available() and pl_module.device.type == "cuda":
            values["perf/gpu_mem_GiB"] = torch.cuda.max_memory_allocated(pl_module.device) / 2 ** 30
            torch.cuda.reset_peak_memory_stats(pl_module.device)
        pl_module.log_dict(values, on_step=True, on_epoch=False)
        self._reset(now)
        self.batch_end = now


def monitors(renders: dict | None = None) -> list:
    """The callbacks of the module docstring, and :class:`~spread.training.renders.SampleRenders` with the
    train config's ``renders`` settings (none when absent or ``every_n_epochs`` ≤ 0)."""
    from lightning.pytorch.callbacks import LearningRateMonitor

    from spread.training.renders import SampleRenders

    out = [LearningRateMonitor(logging_interval="step"), GradientNorm(), Throughput()]
    if renders and int(renders.get("every_n_epochs", 0)) > 0:
        out.append(SampleRenders(**dict(renders)))
    return out
