"""Sweep points (``spread-sample evaluate=true`` run folders) re-used only when their fingerprint matches.

``out_dir/point.json`` records the point's full fingerprint (:func:`spread.runtime.fingerprint.point_identity`),
its short name, where it ran (:func:`~spread.runtime.fingerprint.run_tags`), its status (``running`` from the
moment the work starts, ``finished`` once ``metrics.json`` is written) and, when the folder was redone, why.
The decision (:func:`check_point`, by the platform's one done-check :func:`spread.runtime.fingerprint.done_check`),
for a run with ``evaluate=true``:

| folder holds | decision |
|---|---|
| ``point.json`` with this fingerprint and an evaluation ``metrics.json`` | re-use (nothing runs) |
| ``point.json`` with this fingerprint, not finished | resume (finished scenes and per-scene lines kept) |
| ``point.json`` with another fingerprint | redo; ``redone_because`` names the changed keys (the old ``metrics.json`` goes; sampling and evaluation keep only the scenes and per-scene lines their own fingerprints still match) |
| ``metrics.json`` but no ``point.json`` (made before fingerprints) | redo from scratch, with that reason |
| nothing of a run | a fresh run |

``resume=false`` always redoes from scratch. A run killed after its ``metrics.json`` but before its record said
``finished`` is re-used (and its record completed): ``metrics.json`` is written atomically after every scene of a
run started with this fingerprint (a redo deletes the old one before any work), so it is this fingerprint's result.
"""

from __future__ import annotations

import contextlib
import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

from spread.io import write_json_atomic

from spread.runtime.fingerprint import POINT, point_folder  # noqa: F401 - named here too
from spread.runtime.fingerprint import read_point_record as read_point  # a folder's point.json (None: none, unreadable)
#: the folder, in the sweep folder beside ``points/``, that holds one lock file per point (:func:`point_lock`);
#: outside ``points/``, whose every entry is a point
LOCKS = ".point-locks"

log = logging.getLogger("spread.sweep")


@dataclass
class PointDecision:
    """reuse: the finished folder stands; fresh: redo from scratch (``reason`` says why, None for a new folder);
    fingerprint: the full fingerprint of the config."""

    reuse: bool
    fresh: bool
    reason: str | None
    fingerprint: dict


def check_point(cfg, out_dir, resume: bool = True) -> PointDecision:
    """Re-use, resume or redo ``out_dir`` for the sample command ``cfg`` (typed, or a composed ``DictConfig``;
    module docstring)."""
    from spread.reporting.runs import is_finished_run
    from spread.runtime.fingerprint import done_check, point_fingerprint

    fingerprint = point_fingerprint(cfg)
    record = read_point(out_dir)
    finished = is_finished_run(out_dir)
    decision = done_check(None if record is None else record.get("fingerprint") or {}, fingerprint,
                          present=finished or record is not None, finished=finished, resume=resume,
                          unknown="metrics.json has no fingerprint (made before fingerprints)")
    if decision.reuse:
        other = made_otherwise(out_dir, fingerprint)
        if other:  # another command sampled or evaluated into the folder since: its record no longer says
            return PointDecision(False, True, other, fingerprint)
        damaged = damaged_metrics(out_dir)
        if damaged:  # a hand edit (a NaN, a count of text): resumed, so the evaluation writes it again from its lines
            return PointDecision(False, False, damaged, fingerprint)
        if record.get("status") != "finished":
            finish_point(out_dir)
    return PointDecision(decision.reuse, decision.fresh, decision.reason, fingerprint)


def damaged_metrics(out_dir) -> str | None:
    """Why a finished point's ``metrics.json`` cannot be read as the evaluation writes it (``spread-report`` refuses
    it: :func:`spread.reporting.runs.check_shape`), or None. A sweep re-used such a point, NaN shown as –."""
    from spread.io import read_json_object
    from spread.reporting.runs import RunError, check_shape

    path = Path(out_dir) / "metrics.json"
    try:
        check_shape(path, read_json_object(path))
    except (RunError, ValueError, OSError) as exc:
        return f"its metrics.json is damaged ({' '.join(str(exc).split())[:300]})"
    return None


def made_otherwise(out_dir, fingerprint: dict) -> str | None:
    """Why a point folder whose ``point.json`` matches ``fingerprint`` holds results of other settings (None: it
    does not): its ``sampling.json`` pins another sampling identity, or its ``metrics.json`` records that it measured
    other scenes or with other settings (``sampled_with``, ``evaluated_with``) — a plain ``spread-sample`` or
    ``spread-evaluate`` run into the folder, which does not write ``point.json``. A file that is not there, and
    records a version wrote without these keys, are not asked; a damaged file is a reason."""
    from spread.io import read_json_object
    from spread.runtime.fingerprint import identity_changes

    out, now = Path(out_dir), fingerprint
    sampling_part = {k: v for k, v in now.items() if k not in ("samples_per_graph", "evaluation")}
    records = {}
    for name in ("sampling.json", "metrics.json"):
        try:
            records[name] = read_json_object(out / name) if (out / name).is_file() else {}
        except (OSError, ValueError) as exc:
            return f"its {name} does not read ({exc})"
    manifest, metrics = records["sampling.json"], records["metrics.json"]
    pinned = manifest.get("fingerprint")
    if isinstance(pinned, dict) and "sampling" in pinned:
        changed = identity_changes(pinned, sampling_part)
        if changed:
            return f"its sampling.json was sampled with other settings since ({', '.join(changed[:4])})"
    made = {}
    if isinstance(metrics.get("sampled_with"), dict):
        made |= metrics["sampled_with"]
    if isinstance(metrics.get("evaluated_with"), dict):
        made["evaluation"] = metrics["evaluated_with"]
    changed = identity_changes(made, {k: now.get(k) for k in made})
    if changed:
        return f"its metrics.json measured other scenes or settings ({', '.join(changed[:4])})"
    return None


def start_point(out_dir, decision: PointDecision) -> None:
    """Before any work: clear a stale result (a redo) and record the point as running."""
    from spread.runtime.fingerprint import run_tags, short

    out = Path(out_dir)
    if decision.fresh:
        for stale in ("metrics.json", POINT):
            (out / stale).unlink(missing_ok=True)
    before = read_point(out) or {}
    write_json_atomic(out / POINT, {
        "fingerprint": decision.fingerprint, "short": short(decision.fingerprint), "status": "running",
        "started": time.strftime("%Y-%m-%dT%H:%M:%S"), "tags": run_tags(),
        "redone_because": decision.reason or before.get("redone_because")})


def finish_point(out_dir, seconds: float | None = None) -> dict:
    """After ``metrics.json`` is written: the record says ``finished`` (and the run's wall seconds)."""
    out = Path(out_dir)
    record = read_point(out) or {}
    record.update(status="finished", finished=time.strftime("%Y-%m-%dT%H:%M:%S"))
    if seconds is not None or "seconds" not in record:
        record["seconds"] = seconds
    write_json_atomic(out / POINT, record)
    return record


@contextlib.contextmanager
def point_lock(folder):
    """Hold the point ``folder``'s lock while a trial decides and does its work: an exclusive ``flock`` on
    ``<sweep folder>/.point-locks/<folder name>.lock``, *waiting* when another trial holds it. Two trials of one
    identity (a random search that drew the same values twice) thus never run at once: the second waits for the
    first and then finds its point finished with the same fingerprint, and re-uses it. The kernel releases the
    lock when a process dies, so a killed trial never leaves a stale one."""
    import fcntl

    folder = Path(folder)
    locks = folder.parent.parent / LOCKS
    locks.mkdir(parents=True, exist_ok=True)
    path = locks / f"{folder.name}.lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0), 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("%s: another trial of the same point is running; waiting for it", folder.name)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield path
    finally:
        os.close(fd)
