"""A training loss that is no number (NaN, ±inf) stops the run: :class:`StopOnNonFiniteLoss`.

Before, a run whose loss went NaN (``model.lr=1e30``, an fp16 overflow, a damaged batch) trained on: every later
step wrote NaN weights, its checkpoints held them, sampling then failed or drew nothing, and the command exited 0.
"""

from __future__ import annotations

from lightning.pytorch.callbacks import Callback


class NonFiniteLoss(ValueError):
    """The training loss was NaN or ±inf at a step; the message names the step, the value and what to change (a user
    error: one line on the console, :mod:`spread.cli.user_errors`)."""


class StopOnNonFiniteLoss(Callback):
    """Stops training with :class:`NonFiniteLoss` once a training step's loss is NaN or ±inf, before any checkpoint
    of the weights it updated is saved: the checkpoints on disk keep the last finite weights.

    No host synchronisation per step (the GPU queue stays full): the first such step and its loss are kept on the loss's
    device, and read every ``trainer.log_every_n_steps`` steps, before every checkpoint is written (Ctrl-C's and
    SIGTERM's ``last.ckpt`` too) and at the end of training. Under DDP the ranks agree (one all-reduce a read), so
    they stop together."""

    def __init__(self):
        self._first = None  # (global step, loss) of the first non-finite loss, as 0-d tensors on its device
        self._saved = None  # the global step of the newest checkpoint this run saved or resumed from

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        import torch

        loss = outputs.get("loss") if isinstance(outputs, dict) else outputs
        if not isinstance(loss, torch.Tensor):
            return
        loss = loss.detach().float().reshape(-1)[:1].reshape(())
        if self._first is None:
            self._first = (torch.full((), -1, dtype=torch.long, device=loss.device), torch.zeros((), device=loss.device))
        step, value = self._first
        new = (~torch.isfinite(loss)) & (step < 0)
        self._first = (torch.where(new, torch.full_like(step, int(trainer.global_step)), step),
                       torch.where(new, loss, value))
        every = max(1, int(getattr(trainer, "log_every_n_steps", 50) or 50))
        if trainer.global_step % every == 0:
            self.check(trainer)

    def on_save_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        self.check(trainer)
        self._saved = int(trainer.global_step)

    def on_load_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        self._saved = int(checkpoint.get("global_step", -1))

    def on_train_end(self, trainer, pl_module) -> None:
        self.check(trainer)

    def check(self, trainer) -> None:
        """:class:`NonFiniteLoss` when a step's loss so far was NaN or ±inf (on any rank)."""
        step = int(self._first[0].item()) if self._first is not None else -1
        bad = step >= 0
        if trainer.world_size > 1:
            bad = trainer.strategy.reduce_boolean_decision(bad, all=False)
        if not bad:
            return
        where = f"at step {step} ({float(self._first[1].item())})" if step >= 0 else "on another rank"
        kept = (f"the checkpoints on disk hold finite weights (the newest: step {self._saved})" if self._saved
                else "no checkpoint of this run was saved")
        lr = (getattr(trainer.lightning_module, "hparams", None) or {}).get("lr")
        raise NonFiniteLoss(f"the training loss was not a number {where}: the weights it updated are not numbers "
                            f"either, so training stopped before saving them; {kept}. Lower model.lr"
                            f"{f' (now {lr})' if lr is not None else ''}, set trainer.gradient_clip_val, or check the "
                            f"data")
