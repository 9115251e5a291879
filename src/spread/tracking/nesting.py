"""The open parent run of a sweep, ablation or comparison, as this process's environment names it
(:data:`PARENT_ENV`), and the tags that nest a run under it. On its own so that the MLflow writers
(:mod:`spread.tracking.mlflow_store`) and the parent runs (:mod:`spread.tracking.parent`) both read it without
importing each other."""

from __future__ import annotations

import contextlib
import json
import os
from typing import Iterator

#: The environment variable naming the open parent run (JSON: ``run_id``, ``tracking_uri``, ``experiment_id``,
#: ``kind``).
PARENT_ENV = "SPREAD_MLFLOW_PARENT"


def current_parent() -> dict | None:
    """The parent run named in :data:`PARENT_ENV` (None when none is open)."""
    text = os.environ.get(PARENT_ENV)
    if not text:
        return None
    try:
        parent = json.loads(text)
    except ValueError:
        return None
    return parent if isinstance(parent, dict) and parent.get("run_id") else None


def parent_tags(uri: str) -> dict[str, str]:
    """Tags that nest a run opened now in store ``uri`` under the open parent run (none when there is no parent
    or it lives in another store)."""
    parent = current_parent()
    if parent is None or parent.get("tracking_uri") != uri:
        return {}
    return {"mlflow.parentRunId": str(parent["run_id"]), "spread.parent_kind": str(parent.get("kind") or "")}


@contextlib.contextmanager
def environment(parent: dict | str | None) -> Iterator[None]:
    """:data:`PARENT_ENV` set to ``parent`` while the block runs (None: left as it is), then restored."""
    if parent is None:
        yield
        return
    old = os.environ.get(PARENT_ENV)
    os.environ[PARENT_ENV] = parent if isinstance(parent, str) else json.dumps(parent)
    try:
        yield
    finally:
        os.environ.pop(PARENT_ENV, None) if old is None else os.environ.__setitem__(PARENT_ENV, old)
