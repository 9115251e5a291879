"""Resume from ``per_scene.jsonl``: which scenes are done, without losing or double-counting any.

The driver appends one line per finished scene (:func:`spread.io.append_jsonl`, fsynced). A killed run
can leave a torn last line and, if it is resumed twice over the same folder, duplicates. On start,
:func:`load_finished` reads the lines (skipping a torn one), keeps the first line of each scene id, and
rewrites the file atomically with exactly those lines — so the next append starts on a fresh line (an
append after a torn line would otherwise glue the new line onto the torn one and lose it). A line counts
only for the content it was measured on: each record carries the SHA-256 of its scene file, and a scene
whose file changed since is evaluated again.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Iterable

from spread.io import read_jsonl, write_text_atomic


def dedupe(records: Iterable[dict]) -> dict[str, dict]:
    """First record of each ``scene_id``, in file order (records of one scene are identical by seed)."""
    out: dict[str, dict] = {}
    for r in records:
        if not isinstance(r, dict):  # a hand-edited line that is JSON but no record: dropped, as a torn one
            continue
        sid = r.get("scene_id")
        if isinstance(sid, str) and sid not in out:
            out[sid] = r
    return out


def load_finished(path: str | os.PathLike, retry_failed: bool = False,
                  inputs: dict[str, str] | None = None) -> tuple[dict[str, dict], list[str]]:
    """(finished scenes of a ``per_scene.jsonl``: scene id → record; ids dropped because their input
    changed), and the file compacted to the finished ones.

    ``retry_failed``: drop the records that have an ``error`` so those scenes are evaluated again.
    ``inputs``: scene id → SHA-256 of the scene file now; a record whose ``input_sha256`` differs (the file
    was replaced under the same name, or the record predates input hashes) is dropped and counted, so that
    scene is evaluated again instead of keeping a result of other content.
    """
    path = Path(path)
    if not path.exists():
        return {}, []
    finished = dedupe(read_jsonl(path))
    if retry_failed:
        finished = {k: r for k, r in finished.items() if not r.get("error")}
    changed = []
    if inputs is not None:
        changed = sorted(k for k, r in finished.items() if k in inputs and r.get("input_sha256") != inputs[k])
        finished = {k: r for k, r in finished.items() if k not in changed}
    write_text_atomic(path, "".join(json.dumps(r) + "\n" for r in finished.values()))
    return finished, changed
