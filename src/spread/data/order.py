"""The training order of a split: a function of (seed, position) alone, so a resumed run sees the same batches.

A run killed at step k and resumed from its checkpoint must see exactly the batches the uninterrupted run
would have seen. :class:`EpochOrder` shuffles epoch e with a generator seeded by (seed, e) — not by a
generator advanced through earlier epochs, which a resumed process would not have advanced — and it asks,
each time an epoch's iteration begins, where training stands: ``position()`` → (epoch, items already trained
in it), which the data module derives from the trainer's restored global step. The sampler's body runs when
the loader first draws from it (after Lightning has restored the checkpoint), and ``set_epoch`` is ignored:
Lightning's own epoch counter can differ by one after a mid-epoch stop, the step count cannot.

Object-count-aware batching (``sizes``, ``batch_size``, ``window`` > 0): epoch e's shuffled order is cut into
windows of ``window × batch_size`` items; each window is sorted by object count and cut into batches, and the
epoch's batches are shuffled (the same seeded generator). A batch then holds rooms of similar size, so it is
padded little: the graph transformer's cost grows with the square of the padded object count. Still a function
of (seed, epoch) alone, every item once per epoch, and batches never straddle a resume point (positions are
whole batches).

:class:`StatefulLoader` tells Lightning the loader resumes (it has no state of its own to save: the position
follows the global step Lightning restores).
"""

from __future__ import annotations

import hashlib
import math
from typing import Callable, Sequence

import torch
from torch.utils.data import DataLoader, Sampler


def epoch_seed(seed: int, epoch: int) -> int:
    """A 63-bit seed from (seed, epoch) (SHA-256, so nearby seeds give unrelated orders)."""
    digest = hashlib.sha256(f"spread-order/{int(seed)}/{int(epoch)}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & (2 ** 63 - 1)


def batches_per_epoch(items: int, batch_size: int, limit: int | float = 1.0) -> int:
    """Batches Lightning trains per epoch over ``items`` (``limit_train_batches``: a count or a fraction)."""
    full = math.ceil(items / batch_size)
    if isinstance(limit, int) and not isinstance(limit, bool):  # a count, 1 included (Lightning: 1 batch; 1.0: all)
        return min(full, limit)
    return int(full * float(limit)) if float(limit) < 1.0 else full


class EpochOrder(Sampler):
    """Indices of 0 … n−1 in epoch e's order (:func:`epoch_seed`), from the position training stands at.

    ``position()`` → (epoch, items of that epoch already trained); without it, epochs count up from 0.
    ``per_epoch``: an epoch is the first ``per_epoch`` of the order (distinct indices; default all ``n``), e.g.
    ``len(train)`` of the 8·``len(train)`` (room, symmetry) pairs of an augmented split.
    """

    def __init__(self, n: int, seed: int, position: Callable[[], tuple[int, int]] | None = None,
                 per_epoch: int | None = None, sizes: Callable[[], Sequence[int]] | Sequence[int] | None = None,
                 batch_size: int = 1, window: int = 0):
        self.n, self.seed, self.position = int(n), int(seed), position
        self.per_epoch = self.n if per_epoch is None else int(per_epoch)
        if not 0 < self.per_epoch <= self.n:
            raise ValueError(f"EpochOrder: per_epoch={per_epoch} must be in 1..{self.n}")
        if int(window) < 0:
            raise ValueError(f"data.bucket_batches must be >= 0, got {window}")
        self.batch_size, self.window = int(batch_size), int(window)
        self._sizes = sizes  # object count of every index (or a function giving them, asked on first use)
        self._next_epoch = 0

    def sizes(self) -> list[int]:
        if callable(self._sizes):
            self._sizes = list(self._sizes())
        if len(self._sizes) != self.n:
            raise ValueError(f"EpochOrder: {len(self._sizes)} sizes for {self.n} items")
        return list(self._sizes)

    def set_epoch(self, epoch: int) -> None:  # Lightning calls it; the position decides (module docstring)
        pass

    def order(self, epoch: int) -> list[int]:
        generator = torch.Generator().manual_seed(epoch_seed(self.seed, epoch))
        order = torch.randperm(self.n, generator=generator)[:self.per_epoch].tolist()
        if self.window <= 0 or self._sizes is None:
            return order
        sizes, span, batches = self.sizes(), self.window * self.batch_size, []
        for start in range(0, len(order), span):
            window = sorted(order[start:start + span], key=lambda i: sizes[i])  # stable: ties keep the shuffle
            batches += [window[k:k + self.batch_size] for k in range(0, len(window), self.batch_size)]
        # a short last batch stays last (where an unbucketed epoch has it); the full ones are shuffled
        full = [b for b in batches if len(b) == self.batch_size]
        short = [b for b in batches if len(b) < self.batch_size]
        shuffled = [full[i] for i in torch.randperm(len(full), generator=generator).tolist()]
        return [i for batch in shuffled + short for i in batch]

    def __iter__(self):
        epoch, start = self.position() if self.position is not None else (self._next_epoch, 0)
        self._next_epoch = epoch + 1
        yield from self.order(epoch)[start:]

    def __len__(self) -> int:
        return self.per_epoch


class StatefulLoader(DataLoader):
    """A ``DataLoader`` Lightning treats as resumable: its order follows the restored global step."""

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass
