"""torch's thread count as a setting: one check for every command that takes ``threads`` (sampling, training)."""

from __future__ import annotations


def check_threads(threads) -> None:
    """``threads``: torch threads per process, a whole number ≥ 1 or None (torch's default); ``ValueError`` by key."""
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise ValueError(f"threads={threads!r}: expected a whole number ≥ 1, or null for torch's default")
