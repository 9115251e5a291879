"""A stage's begun-with inputs (:class:`~spread.experiments.stages.Ledger`): written when a stage begins, removed
when the ledger records it, so a driver stopped mid-stage leaves what the stage's outputs were begun with. One file
per stage beside the ledger (``<ledger's folder>/.begun/<stage, / as __>.json``): concurrent stages (Ray tasks,
:mod:`spread.experiments.stage_pool`) never write the same file."""

from __future__ import annotations

import time
from pathlib import Path

from spread.io import read_json, write_json_atomic


def begun_file(ledger: Path, name: str) -> Path:
    """Where a stage's begun-with inputs lie: ``<ledger's folder>/.begun/<name, / as __>.json`` — one file per stage,
    so concurrent stages (Ray tasks) never write the same file."""
    return Path(ledger).parent / ".begun" / (name.replace("/", "__") + ".json")


def mark_begun(ledger: Path, name: str, inputs: dict) -> None:
    """Record that the stage ``name`` of the ledger at ``ledger`` begins with ``inputs`` (atomic)."""
    target = begun_file(ledger, name)
    target.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(target, {"name": name, "inputs": inputs, "started": time.strftime("%Y-%m-%dT%H:%M:%S")})


def read_begun(ledger: Path, name: str) -> dict | None:
    """The inputs the stage ``name`` last began with and did not finish (None: none, or an unreadable record)."""
    try:
        record = read_json(begun_file(ledger, name))
    except (OSError, ValueError):
        return None
    return record.get("inputs") if isinstance(record, dict) and record.get("name") == name else None


def forget_begun(ledger: Path, name: str) -> None:
    """The stage ``name`` is recorded in the ledger at ``ledger``: its begun-with record goes."""
    begun_file(ledger, name).unlink(missing_ok=True)
