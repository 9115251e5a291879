"""Counting the kernel operators a piece of torch code dispatches: how launch-bound it is on a GPU.

On a GPU every dispatched ATen operator that computes is at least one kernel launch (~5–10 µs of CPU time
in eager mode), so a step of many small operators is bound by launches, not arithmetic. :class:`OperatorCounter`
is a ``TorchDispatchMode`` that counts the operators reaching the backends, forward and backward alike, leaving
out those that only make a new view of existing memory or read metadata (``view``, ``permute``, ``expand``,
``slice``, ``detach``, ``t``, …: no kernel runs) and tensor-factory calls that only allocate (``empty``). What
is left — arithmetic, copies, reductions, fills, indexing, the fused attention, a custom operator — is counted
once per call. A custom operator (``spread::…``, e.g. the dense nearest-point search) counts once: its CUDA
implementation is one kernel launch; what its CPU fallback does inside is not seen.

Works on CPU tensors, so the count of a GPU step is measured without a GPU (the same operators are dispatched,
up to backend-specific decompositions such as which fused attention kernel runs).
"""

from __future__ import annotations

from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

#: Operators whose result the host must read before it can go on (the output's size or value): each one stalls the
#: host until the device has caught up. Counted apart as ``syncs`` (those that also launch are counted there too).
HOST_READS = frozenset({"_local_scalar_dense", "nonzero", "masked_select", "_unique2", "unique_dim",
                        "unique_consecutive"})


def _bool_indexing(name: str, args) -> bool:
    """``x[mask]`` / ``x[mask] = v``: indexing by a boolean tensor finds its True entries on the host."""
    if name not in ("index", "index_put", "index_put_") or len(args) < 2:
        return False
    return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in (args[1] or ()))
#: Operators that allocate or alias without running a kernel (beyond those whose schema says they are views).
METADATA_ONLY = frozenset({
    "detach", "alias", "_unsafe_view", "lift_fresh", "empty", "empty_like", "empty_strided", "_reshape_alias",
    "set_", "resize_", "sym_size", "sym_stride", "sym_numel", "sym_storage_offset", "is_same_size",
    "_local_scalar_dense",  # a host read (.item()): a synchronisation, not a launch; counted apart
    "_to_copy_noop", "prim_layout", "_has_compatible_shallow_copy_type", "_nested_tensor_size",
    "is_nonzero", "_shape_as_tensor",
})


def is_kernel(func) -> bool:
    """Whether an ATen overload (``torch.ops.aten.add.Tensor``) runs a kernel (module docstring)."""
    if getattr(func, "is_view", False):
        return False
    name = func._schema.name.split("::")[-1]
    return name not in METADATA_ONLY


class OperatorCounter(TorchDispatchMode):
    """``with OperatorCounter() as c: ...`` then ``c.total`` (kernel operators), ``c.by_name`` (Counter of
    operator names), ``c.syncs`` (host reads: ``.item()``, ``bool(tensor)``, ``nonzero``, boolean indexing, …)."""

    def __init__(self):
        super().__init__()
        self.by_name: Counter = Counter()
        self.syncs = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = func._schema.name.split("::")[-1]
        if name in HOST_READS or _bool_indexing(name, args):
            self.syncs += 1
        if is_kernel(func):
            self.by_name[f"{func._schema.name.split('::')[0]}::{name}"] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.by_name.values())


def count_operators(fn, *args, **kwargs) -> tuple[int, Counter, object]:
    """(kernel operators, their names, fn's result) of one call ``fn(*args, **kwargs)``."""
    with OperatorCounter() as counter:
        out = fn(*args, **kwargs)
    return counter.total, counter.by_name, out
