"""Checkpoints of a training run: atomic writes, the final state, which checkpoint a run resumes from.

The run folder's ``checkpoints/`` holds ``last.ckpt`` (what ``ckpt_path=last`` resumes) and the newest
periodic one. ``ckpt_path``: ``null`` starts a new run; a path resumes from that checkpoint (weights, EMA,
optimizer, global step, loop state); ``last`` resumes ``<run folder>/checkpoints/last.ckpt`` when it
exists, else the newest ``<paths.runs_dir>/train/<experiment_name>/*/checkpoints/last.ckpt``, else starts a
new run (so a preempted job can always be relaunched with ``ckpt_path=last out_dir=<its folder>``). Ctrl-C and
SIGTERM (a scheduler's preemption) stop at the end of the step in progress and save it as ``last.ckpt``
(:func:`stop_on_interrupt`).
"""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path
from typing import Callable, Iterator

from lightning.pytorch.callbacks import Callback
from omegaconf import DictConfig

log = logging.getLogger("spread.train")


def resolve_ckpt_path(cfg: DictConfig, run_dir: Path) -> Path | None:
    """The checkpoint to resume from, following the rules of the module docstring."""
    value = cfg.get("ckpt_path")
    if value in (None, "", "null"):
        return None
    if str(value) != "last":
        path = Path(str(value))
        if not path.is_file():
            raise SystemExit(f"spread-train: ckpt_path={value}: no such checkpoint file")
        return path
    own = run_dir / "checkpoints" / "last.ckpt"
    if own.is_file():
        return own
    runs = Path(str(cfg.paths.runs_dir)) / "train" / str(cfg.experiment_name)
    found = sorted(runs.glob("*/checkpoints/last.ckpt"), key=lambda p: p.stat().st_mtime)
    if found:
        return found[-1]
    log.warning("ckpt_path=last: no last.ckpt in %s or under %s; starting a new run", own.parent, runs)
    return None


class CheckpointStep(Callback):
    """Remembers the global step of the newest checkpoint this run saved or resumed from."""

    def __init__(self):
        self.step: int | None = None

    def on_save_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        self.step = int(trainer.global_step)

    def on_load_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        self.step = int(checkpoint.get("global_step", -1))


def save_final_checkpoint(trainer, run_dir: Path, newest: CheckpointStep) -> None:
    """``checkpoints/last.ckpt`` = the state at the end of ``fit``, when no checkpoint holds it yet.
    ModelCheckpoint saves "last" only at its own moments (every n steps, epoch ends), so a run stopped by
    ``max_time`` mid-epoch would otherwise leave a last.ckpt behind the trained weights. A resumed run that
    takes no step leaves the file untouched (same bytes, so samplers keyed on its hash stay valid)."""
    if trainer.fast_dev_run or trainer.checkpoint_callback is None or trainer.global_step == 0:
        return
    if newest.step != trainer.global_step:
        trainer.save_checkpoint(run_dir / "checkpoints" / "last.ckpt")


def atomic_checkpoint_io():
    """A Lightning ``TorchCheckpointIO`` that loads through :func:`spread.safe_load.load_checkpoint` and writes each checkpoint to a temp file beside its target and
    renames it (:func:`spread.io.atomic_path`): a job killed mid-save never leaves a torn ``last.ckpt``, also
    when TMPDIR is on another filesystem than the run folder (where a rename falls back to a copy)."""
    import torch
    from lightning.pytorch.plugins.io import TorchCheckpointIO

    from spread.io import atomic_path

    class AtomicCheckpointIO(TorchCheckpointIO):
        def save_checkpoint(self, checkpoint, path, storage_options=None) -> None:
            if storage_options is not None:
                raise TypeError(f"AtomicCheckpointIO: storage_options are not supported (got {storage_options!r})")
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(path) as tmp:
                torch.save(checkpoint, tmp)

        def load_checkpoint(self, path, map_location=None, weights_only=None):
            """Every checkpoint Lightning loads (``ckpt_path=``) goes through the platform's loader:
            ``weights_only=True`` whatever ``weights_only`` or ``TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD`` say, a
            damaged file named (:func:`spread.safe_load.load_checkpoint`)."""
            from spread.safe_load import load_checkpoint

            return load_checkpoint(path, map_location="cpu" if map_location is None else map_location)

    return AtomicCheckpointIO()


class StopRequested(Exception):
    """Ctrl-C or SIGTERM: training stopped at an optimiser step's end, that step saved as ``last.ckpt``
    (:class:`StopAtStep`)."""


class StopAtStep(Callback):
    """Stops training at the end of the first optimiser step after Ctrl-C (:func:`stop_on_interrupt` sets
    ``asked``): saves ``last`` there and raises :class:`StopRequested`, which Lightning tears down and lets through.
    A step, not a batch: with ``accumulate_grad_batches`` a stop inside an accumulation would save a data position
    the resumed run cannot take up. Under DDP the ranks agree on the step (one all-reduce a step), so they stop
    together. Not Lightning's ``should_stop``: that runs a validation pass first."""

    def __init__(self, last: Path):
        self.last = Path(last)
        self.asked: str | bool = False  # the signal's name once one came ("Ctrl-C", "SIGTERM")
        self.sigterm = None  # the SIGTERM handler of :func:`stop_on_interrupt`, while it is in force
        self._step = None

    def on_train_start(self, trainer, *args) -> None:
        """Lightning's fit put its own SIGTERM handler in (it raises ``SIGTERMException`` at the end of the batch,
        mid-accumulation too, and nothing is saved): ours again, so SIGTERM stops at a step's end like Ctrl-C.
        Lightning's teardown restores the handler it found (ours)."""
        import signal

        if self.sigterm is not None:
            signal.signal(signal.SIGTERM, self.sigterm)

    def on_train_batch_start(self, trainer, *args) -> None:
        self._step = trainer.global_step

    def on_train_batch_end(self, trainer, *args) -> None:
        if trainer.global_step == self._step:  # inside an accumulation: no step ended
            return
        asked = self.asked
        if trainer.world_size > 1:
            asked = trainer.strategy.reduce_boolean_decision(asked, all=False)
        if asked:
            trainer.save_checkpoint(self.last)
            raise StopRequested(trainer.global_step)


@contextlib.contextmanager
def stop_on_interrupt(stopper: StopAtStep) -> Iterator[StopAtStep]:
    """Ctrl-C or SIGTERM while the block runs (a fit): the first asks ``stopper`` to stop at the end of the step in
    progress (the caller then raises KeyboardInterrupt, or ``SystemExit(143)`` for SIGTERM), a second one stops at
    once (Lightning's own shutdown; nothing is saved). Before, Lightning turned Ctrl-C into a "graceful shutdown"
    that saved nothing (up to ``checkpoint.every_n_train_steps`` steps lost) and exited 1, which a study took for a
    failed stage and went on;
    SIGTERM (a scheduler's preemption) saved nothing and exited 0, a finished run to the scheduler, with no word.
    Only in the main thread (a signal handler is set there only: a Ray Train worker's fit runs in another); a signal
    the process ignores (SIGINT under ``nohup`` or in a shell's background job) stays ignored."""
    import signal
    import sys
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield stopper  # another thread (a Ray Train worker's fit): as is
        return
    from spread.runtime.ray import TERMINATED

    def handler(signum, frame):
        name = "Ctrl-C" if signum == signal.SIGINT else "SIGTERM"
        if stopper.asked:  # the second signal: now
            if signum == signal.SIGINT:
                raise KeyboardInterrupt
            raise SystemExit(TERMINATED)
        stopper.asked = name
        print(f"spread-train: {name}: stopping at the end of this step and saving it ({name} again: stop now)",
              file=sys.stderr, flush=True)

    previous = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    for sig, was in previous.items():  # a process that ignores it (nohup, a shell's background job): as is
        if was is not signal.SIG_IGN:
            signal.signal(sig, handler)
    stopper.sigterm = handler if previous[signal.SIGTERM] is not signal.SIG_IGN else None
    try:
        yield stopper
    finally:
        stopper.sigterm = None
        for sig, was in previous.items():  # None: a handler set outside Python, which cannot be set again
            signal.signal(sig, was if was is not None else signal.SIG_DFL)
