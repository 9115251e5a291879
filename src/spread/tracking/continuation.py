"""A relaunched sampling or evaluation run continues its tracker runs (as a resumed training run does).

Without this, every launch of ``spread-sample`` or ``spread-evaluate`` into one folder opened a new MLflow and
wandb run: a killed launch stayed ``RUNNING`` on the dashboard forever beside the relaunch that finished its
work, and a comparison of runs counted the folder twice. Now a launch records in its folder's :data:`RECORD`,
once its checks passed, the job type, a digest of the identity of its results (what they depend on: the
sampling identity with the samples per graph for ``spread-sample``, the evaluation identity with the scenes'
content for ``spread-evaluate``; :mod:`spread.runtime.fingerprint`) and its runs' ids. A later launch into the
same folder with ``resume=true``, the same job type and the same identity continues the recorded runs: the
MLflow run when it is in the same store (status back to ``RUNNING``, its params kept, tag ``spread.launches``
counted up, moved under the parent run open now; :func:`spread.tracking.mlflow_store.open_run`), and the wandb
run (same id, ``resume="allow"``). Anything else (``resume=false``, other settings, another store, no record)
opens new runs, as before: their numbers are other numbers.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

#: The file in a run folder that says which job and identity its tracker runs hold.
RECORD = "tracked_with.json"


class Continuation:
    """One launch's answer for ``out_dir``: ``identity()`` gives the identity of its results (called only when a
    tracker asks); ``resume``: the command's ``resume``."""

    def __init__(self, out_dir: str | os.PathLike, job_type: str, identity: Callable[[], dict], resume: bool):
        self.out_dir, self.job_type, self.identity, self.resume = Path(out_dir), job_type, identity, bool(resume)
        self._digest: str | None = None

    @property
    def digest(self) -> str:
        from spread.runtime.fingerprint import digest, normalised

        if self._digest is None:
            self._digest = digest(normalised(self.identity()))
        return self._digest

    def previous(self) -> dict:
        """The folder's record when this launch continues its runs (module docstring), else ``{}``."""
        from spread.io import read_json_object

        path = self.out_dir / RECORD
        if not self.resume or not path.is_file():
            return {}
        try:
            before = read_json_object(path)
            same = before.get("job_type") == self.job_type and before.get("identity") == self.digest
        except (OSError, ValueError):  # a damaged record, or inputs the run's own checks will refuse: new runs
            return {}
        return before if same else {}

    def wandb_id(self) -> str | None:
        """The id of the folder's recorded wandb run to continue, else None (a new run)."""
        found = self.previous().get("wandb_id")
        return str(found) if found else None

    def mlflow_run_id(self, uri: str) -> str | None:
        """The folder's recorded MLflow run to continue when it is in store ``uri``, else None."""
        found = self.previous().get("mlflow") or {}
        return str(found["run_id"]) if isinstance(found, dict) and found.get("tracking_uri") == uri \
            and found.get("run_id") else None

    def record(self, mlflow_run=None, wandb_run=None) -> None:
        """Write :data:`RECORD` (atomically) naming this launch's runs; called once its checks passed (a launch
        refused by them leaves the record of the last one that worked)."""
        from spread.io import write_json_atomic

        if wandb_run is not None and getattr(getattr(wandb_run, "settings", None), "mode", None) == "disabled":
            wandb_run = None  # nothing written, nothing to continue
        if mlflow_run is None and wandb_run is None:
            return
        try:
            identity = self.digest
        except (OSError, ValueError):  # an input the run records as refused (a FIFO scene file): no continuation
            (self.out_dir / RECORD).unlink(missing_ok=True)
            return
        self.out_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.out_dir / RECORD, {
            "job_type": self.job_type, "identity": identity,
            "mlflow": {"tracking_uri": mlflow_run.uri, "run_id": mlflow_run.run_id} if mlflow_run else None,
            "wandb_id": getattr(wandb_run, "id", None) if wandb_run is not None else None})

    def recorded(self, before_work: Callable[[], None] | None, mlflow_run=None, wandb_run=None) -> Callable[[], None]:
        """``before_work`` (a run's hook once its checks passed), then :meth:`record`."""

        def hook() -> None:
            if before_work is not None:
                before_work()
            self.record(mlflow_run, wandb_run)

        return hook
