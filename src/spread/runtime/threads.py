"""torch's thread count as a setting: one check for every command that takes ``threads`` (sampling, training)."""

from __future__ import annotations


def check_threads(threads) -> None:
    """``threads``: torch threads per process, a whole number ≥ 1 or None (torch's default); ``ValueError`` by key."""
    from spread.checks import whole_number

    whole_number(threads, "threads", 1, null="torch's default")
