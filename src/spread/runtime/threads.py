"""torch's thread count as a setting: one check for every command that takes ``threads`` (sampling, training)."""

from __future__ import annotations


def check_threads(threads) -> None:
    """``threads``: torch threads per process, a whole number ≥ 1 or None (torch's default); ``ValueError`` by key."""
    from spread.checks import whole_number

    whole_number(threads, "threads", 1, null="torch's default")


def set_threads(threads: int | None) -> None:
    """torch intra-op threads (None: torch's default). One thread is much faster on a shared 2-core CPU. Imports torch
    only (a study's frame sets it before its checks: Lightning's import, ~7 s of CPU, waits for the work)."""
    check_threads(threads)
    if threads:
        import torch

        torch.set_num_threads(int(threads))
