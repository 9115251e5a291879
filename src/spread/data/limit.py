"""The object limit a sampling or evaluation run applies to its scenes (``max_objects``), shared by both.

A scene of more objects than the limit is left out by name before any work: sampling's geometry model and
evaluation's Col_mesh and Stability grow with the square of the objects (a 130-object room: one Stability run
88 s), so one room far beyond the dataset's holds up its batch or its worker for minutes.
"""

from __future__ import annotations

from pathlib import Path


def object_limit(data_root: str | Path, max_objects: int | None) -> int | None:
    """The largest scene a run takes: ``max_objects``, or (None) twice the largest scene of ``data_root``'s
    ``stats.json`` (None when it does not say); 0 or less: no limit."""
    if max_objects is not None:
        return int(max_objects) if int(max_objects) > 0 else None
    stats = Path(data_root) / "stats.json"
    if not stats.is_file():
        return None
    from spread.io import read_json_object

    largest = read_json_object(stats).get("max_objects")  # a file that is not a JSON object: named
    return 2 * int(largest) if isinstance(largest, int) and not isinstance(largest, bool) and largest > 0 else None


def object_count(path: str | Path) -> int | None:
    """The number of objects of the scene file at ``path`` (the length of its ``asset_id``, the one array read),
    or None when the file does not read as a scene (its reader names why, where the scene is measured)."""
    import numpy as np

    from spread.io import check_input_file
    from spread.safe_load import load_npz

    path = Path(path)
    try:
        check_input_file(path, root=path.parent)
        with load_npz(path) as data:
            ids = data["asset_id"] if "asset_id" in data.files else None
    except Exception:  # noqa: BLE001 - refused, unsafe, torn or not a zip: its reader names why
        return None
    # a zip whose members are not .npy files gives bytes
    return int(ids.reshape(-1).shape[0]) if isinstance(ids, np.ndarray) and ids.dtype.kind in "US" else None


def scenes_over(files, limit: int | None) -> dict[Path, int]:
    """The scene files of ``files`` holding more than ``limit`` objects (None: no limit), each with its count: counted
    by :func:`object_count`, and each one over the limit read as a scene (shapes and values checked, not its assets),
    so a damaged file (an ``asset_id`` of 50 beside poses of 3) is left to its reader to name, never called large."""
    from spread.scene import SceneFormatError, read_scene

    if limit is None:
        return {}
    out = {}
    for f in map(Path, files):
        n = object_count(f)
        if n is None or n <= limit:
            continue
        try:
            read_scene(f)
        except (SceneFormatError, OSError, ValueError):
            continue
        out[f] = n
    return out
