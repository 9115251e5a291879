"""Exponential moving average of a network's weights, as a submodule (so it is in ``state_dict``:
saved in every checkpoint, restored on resume and by ``load_from_checkpoint``).

``decay_t = min(decay, (1 + n) / (10 + n))`` after n updates (the usual warm-up, so early averages
are not dominated by the random initialisation). Buffers (e.g. the translation bounds) are copied.
The averaged copy never requires gradients; its users put it in eval mode (Lightning does for
validation, ``SceneDiffusion.sample_states`` does while sampling).
"""

from __future__ import annotations

import copy

import torch
from torch import nn


class EMA(nn.Module):
    def __init__(self, model: nn.Module, decay: float = 0.999, warmup: bool = True):
        super().__init__()
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"EMA decay must be in [0, 1), got {decay}")
        self.decay, self.warmup = float(decay), bool(warmup)
        self.module = copy.deepcopy(model).requires_grad_(False)
        self.register_buffer("num_updates", torch.zeros((), dtype=torch.long))

    def current_decay(self) -> float:
        n = self._count()
        return min(self.decay, (1 + n) / (10 + n)) if self.warmup else self.decay

    def _count(self) -> int:
        """Updates so far, kept on the host too: read from the buffer once (after a load), not at every step."""
        if getattr(self, "_host_count", None) is None or self._host_version != self.num_updates._version:
            self._host_count, self._host_version = int(self.num_updates), self.num_updates._version
        return self._host_count

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        weight = 1.0 - self.current_decay()
        self._host_count += 1
        ema_params = list(self.module.parameters())
        params = [p.detach().to(e.dtype) for e, p in zip(ema_params, model.parameters())]
        torch._foreach_lerp_(ema_params, params, weight)
        for e, b in zip(self.module.buffers(), model.buffers()):
            e.copy_(b)
        self.num_updates += 1
        self._host_version = self.num_updates._version

    def forward(self, *args, **kwargs):
        return self.module(*args, **kwargs)
