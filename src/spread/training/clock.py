"""What a training run has spent: optimiser steps, scenes seen and training seconds, for quality-against-compute
curves (``benchmarks/learning_curve.py``) and wandb.

:class:`TrainingClock` counts the wall seconds of the training loop — data loading, forward, backward,
optimiser, logging — and leaves out validation (and the sampling it may do), so a run that validates often is
not charged for it. ``scenes`` counts the training scenes seen (every rank's batch). Both are logged as
``train/seconds`` and ``train/scenes`` with every training log, kept in the checkpoint (a resumed run goes on
counting), and appended with the step to ``<run folder>/clock.jsonl`` each time a checkpoint is saved, so each
checkpoint can be placed on the step, scene and time axes afterwards.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

from lightning.pytorch.callbacks import Callback


class TrainingClock(Callback):
    def __init__(self, run_dir: str | Path | None = None):
        self.run_dir = None if run_dir is None else Path(run_dir)
        self.seconds = 0.0
        self.scenes = 0
        self._since: float | None = None

    # ---- the clock runs in the training loop only -----------------------------------------------
    def _start(self) -> None:
        self._since = time.perf_counter()

    def _stop(self) -> None:
        if self._since is not None:
            self.seconds += time.perf_counter() - self._since
            self._since = None

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._start()

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self._stop()

    def on_validation_start(self, trainer, pl_module) -> None:
        self._stop()

    def on_validation_end(self, trainer, pl_module) -> None:
        if trainer.training:
            self._start()

    def on_train_end(self, trainer, pl_module) -> None:
        self._stop()

    def elapsed(self) -> float:
        return self.seconds + (time.perf_counter() - self._since if self._since is not None else 0.0)

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.scenes += int(batch["x"].shape[0]) * int(trainer.world_size)
        pl_module.log_dict({"train/seconds": self.elapsed(), "train/scenes": float(self.scenes)},
                           on_step=True, on_epoch=False, batch_size=int(batch["x"].shape[0]))

    # ---- saved with the checkpoint, appended to clock.jsonl ---------------------------------------
    def on_save_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        record = {"step": int(trainer.global_step), "scenes": self.scenes, "seconds": round(self.elapsed(), 3)}
        if self.run_dir is not None and trainer.is_global_zero:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            with open(self.run_dir / "clock.jsonl", "a") as f:
                f.write(json.dumps(record) + "\n")

    def state_dict(self) -> dict:
        return {"seconds": self.elapsed(), "scenes": self.scenes}

    def load_state_dict(self, state_dict: dict) -> None:
        self.seconds = float(state_dict.get("seconds", 0.0))
        self.scenes = int(state_dict.get("scenes", 0))


def last_record(run_dir: str | Path) -> dict | None:
    """The last record ``{"step", "seconds"}`` of a run's ``clock.jsonl`` (None if it has none), read through the
    bounded-read door; a record that is not one (a line cut by a kill, a non-positive count) is a ValueError naming
    the file."""
    from spread.io import read_text_checked

    path = Path(run_dir) / "clock.jsonl"
    lines = [line for line in read_text_checked(path).splitlines() if line.strip()] if path.is_file() else []
    if not lines:
        return None
    try:
        record = json.loads(lines[-1])
        step, seconds = int(record["step"]), float(record["seconds"])
    except (ValueError, TypeError, KeyError) as exc:
        raise ValueError(f"{path}: the last line is not a clock record ({type(exc).__name__}: {exc})") from exc
    if step < 1 or not math.isfinite(seconds) or seconds <= 0:
        raise ValueError(f"{path}: the last record has step {step} and seconds {seconds}; both must be > 0")
    return {"step": step, "seconds": seconds}
