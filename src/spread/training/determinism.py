"""A resumed training run continues exactly as the uninterrupted one (one process; DDP: see below).

What a training step draws — diffusion noise and timesteps, graph dropout, dropout masks — comes from
torch's global generator. :class:`ExactResume` reseeds it at the start of every step from (seed, global
step, rank), so a step's randomness is a function of the step alone, not of how many steps this process
ran before (a resumed process starts its generator afresh). The batch order is a function of (seed,
epoch) and of the restored global step (:mod:`spread.data.order`). Weights, EMA, optimizer state and the
loop's progress are Lightning's checkpoint. So a run SIGKILLed at step k and resumed with ``ckpt_path=last``
reaches step n with the uninterrupted run's weights and loss, bit for bit on the same machine
(``tests/test_robustness.py``).

Under DDP (more than one process) Lightning replaces the sampler by its distributed one, whose order is a
function of (its seed, epoch) but which restarts an interrupted epoch from its beginning; the noise is still
per step. That is the one difference there.
"""

from __future__ import annotations

import hashlib

import torch
from lightning.pytorch.callbacks import Callback


def step_seed(seed: int, step: int, rank: int = 0) -> int:
    digest = hashlib.sha256(f"spread-step/{int(seed)}/{int(step)}/{int(rank)}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & (2 ** 63 - 1)


class ExactResume(Callback):
    """Reseeds torch at each training step from (seed, global step, rank) (module docstring)."""

    def __init__(self, seed: int):
        self.seed = int(seed)

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx: int) -> None:
        torch.manual_seed(step_seed(self.seed, trainer.global_step, trainer.global_rank))
