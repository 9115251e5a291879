"""Resume from ``per_scene.jsonl``: which scenes are done, without losing or double-counting any.

The driver appends one line per finished scene (:func:`spread.io.append_jsonl`, fsynced). A killed run
can leave a torn last line and, if it is resumed twice over the same folder, duplicates. On start,
:func:`load_finished` reads the lines (skipping a torn one), keeps the first line of each scene id, and
rewrites the file atomically with exactly those lines — so the next append starts on a fresh line (an
append after a torn line would otherwise glue the new line onto the torn one and lose it).
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
        sid = r.get("scene_id")
        if isinstance(sid, str) and sid not in out:
            out[sid] = r
    return out


def load_finished(path: str | os.PathLike, retry_failed: bool = False) -> dict[str, dict]:
    """Finished scenes of a ``per_scene.jsonl`` (scene id → record), and the file compacted to them.

    ``retry_failed``: drop the records that have an ``error`` so those scenes are evaluated again.
    """
    path = Path(path)
    if not path.exists():
        return {}
    finished = dedupe(read_jsonl(path))
    if retry_failed:
        finished = {k: r for k, r in finished.items() if not r.get("error")}
    write_text_atomic(path, "".join(json.dumps(r) + "\n" for r in finished.values()))
    return finished
