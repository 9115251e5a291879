"""A relaunched sampling or evaluation run continues its tracker runs (as a resumed training run does).

Without this, every launch of ``spread-sample`` or ``spread-evaluate`` into one folder opened a new MLflow and
wandb run: a killed launch stayed ``RUNNING`` on the dashboard forever beside the relaunch that finished its
work, and a comparison of runs counted the folder twice. Now a launch records in its folder's :data:`RECORD`,
once its checks passed, the job type, a digest of the identity of its results (what they depend on: the
sampling identity with the samples per graph for ``spread-sample``, the evaluation identity with the scenes'
content for ``spread-evaluate``; :mod:`spread.runtime.fingerprint`), a digest of its config and its runs' ids,
one entry per job type (a sampling folder holds its own evaluation) and command config. A later launch into the
same folder with ``resume=true``, the same job type, the same identity and the same command config (params,
experiment, run name, tags, ``out_dir``: what the runs' record says) continues the recorded runs: the
MLflow run when it is in the same store (status back to ``RUNNING``, its params kept, tag ``spread.launches``
counted up, moved under the parent run open now; :func:`spread.tracking.mlflow_store.open_run`), and the wandb
run (same id, ``resume="allow"``). Anything else (``resume=false``, other settings, another store, no record)
opens new runs, as before: their numbers are other numbers. A continued run that then fails is ``FAILED``: its
status is its last launch's.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

#: The file in a run folder that says which job and identity its tracker runs hold: job type → command config
#: digest → the results' identity digest and the runs' ids.
RECORD = "tracked_with.json"
#: Configs remembered per job type (a launch with other settings, then one with the first settings again,
#: continues the first run).
KEPT = 16


class Continuation:
    """One launch's answer for ``out_dir``: ``identity()`` gives the identity of its results (called only when a
    tracker asks); ``config``: the command's composed config, as its runs log it (params, experiment, run name,
    tags, ``out_dir``); ``resume``: the command's ``resume``."""

    def __init__(self, out_dir: str | os.PathLike, job_type: str, identity: Callable[[], dict], resume: bool,
                 config: dict | None = None):
        from spread.runtime.fingerprint import digest

        self.out_dir, self.job_type, self.identity, self.resume = Path(out_dir), job_type, identity, bool(resume)
        self.config = digest({k: v for k, v in (config or {}).items() if k != "resume"})  # how to launch, not what
        self._digest: str | None = None

    @property
    def digest(self) -> str:
        from spread.runtime.fingerprint import digest, normalised

        if self._digest is None:
            self._digest = digest(normalised(self.identity()))
        return self._digest

    def entries(self) -> dict:
        """The folder's record: job type → config digest → entry (``{}`` without one, or for a damaged one)."""
        from spread.io import read_json_object

        path = self.out_dir / RECORD
        try:
            found = read_json_object(path) if path.is_file() else {}
        except (OSError, ValueError):
            return {}
        return {k: v for k, v in found.items() if isinstance(v, dict)}

    def previous(self) -> dict:
        """This job's entry in the folder's record when this launch continues its runs (module docstring), else
        ``{}``: the same results' identity and the same command config (a changed experiment, run name, tag, param
        or a copied folder's other ``out_dir`` is another run, whose record the old one's params would contradict)."""
        if not self.resume:
            return {}
        before = (self.entries().get(self.job_type) or {}).get(self.config)
        if not isinstance(before, dict):
            return {}
        try:
            same = before.get("identity") == self.digest
        except (OSError, ValueError):  # inputs the run's own checks will refuse: new runs
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
        """Write this job's entry of :data:`RECORD` (atomically; another job's entry — the evaluation a sampling
        folder holds — is kept) naming this launch's runs; called once its checks passed (a launch refused by them
        leaves the record of the last one that worked)."""
        from spread.io import write_json_atomic

        if wandb_run is not None and getattr(getattr(wandb_run, "settings", None), "mode", None) == "disabled":
            wandb_run = None  # nothing written, nothing to continue
        if mlflow_run is None and wandb_run is None:
            return
        entries = self.entries()
        runs = {k: v for k, v in (entries.get(self.job_type) or {}).items()
                if isinstance(v, dict) and k != self.config}
        try:
            identity = self.digest
        except (OSError, ValueError):  # an input the run records as refused (a FIFO scene file): no continuation
            identity = None
        if identity is not None:  # the newest last; the oldest beyond KEPT dropped
            runs[self.config] = {
                "identity": identity,
                "mlflow": {"tracking_uri": mlflow_run.uri, "run_id": mlflow_run.run_id} if mlflow_run else None,
                "wandb_id": getattr(wandb_run, "id", None) if wandb_run is not None else None}
        entries[self.job_type] = dict(list(runs.items())[-KEPT:])
        self.out_dir.mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.out_dir / RECORD, entries)

    def recorded(self, before_work: Callable[[], None] | None, mlflow_run=None, wandb_run=None) -> Callable[[], None]:
        """``before_work`` (a run's hook once its checks passed), then :meth:`record`."""

        def hook() -> None:
            if before_work is not None:
                before_work()
            self.record(mlflow_run, wandb_run)

        return hook
