"""Read once per process: the checkpoint, asset libraries, scene files and file hashes a run needs.

One ``spread-sample`` run used to read its checkpoint three times (the safety check, its sha256, the
worker's load), each conditioning graph three times (the graph list, the worker's dataset, the renders)
and the asset library four times. Here each is read on first use and kept for the life of the process —
the driver, a Ray actor, a Ray task worker, a Ray Tune trial process re-used across trials — so a second
use, or a second trial in the same process, reads nothing.

An entry's key is what it was read from: the file's identity and content stamp — its resolved path, device,
inode, size, modification time and status-change time (ns) — plus the arguments that change the result. A
file changed on disk is read again: rewritten (another size, mtime or ctime), or replaced by another file (another
inode), even one of the same size whose mtime was set back (``touch -d``, ``cp -p``, ``rsync -t``: the kernel sets
ctime to now on every write and every ``utime``, and no program can set it back); a read
that raises is not kept (the next call reads, and raises, again). Each kind of entry lives in its own
bounded table (least recently used dropped first, :data:`LIMITS`). Callers must not modify what they get:
the same object is handed to every caller of the process.

``SPREAD_READ_ONCE=0`` in the environment turns the tables off (every call reads: the "before" of
``benchmarks/bench_warm_trials.py``). :func:`counts` says how many reads (misses) and hits each kind had.
"""

from __future__ import annotations

import os
import threading
from collections import Counter, OrderedDict
from pathlib import Path
from typing import Callable, Hashable

#: Entries kept per kind (least recently used dropped first); other kinds: :data:`DEFAULT_LIMIT`.
LIMITS = {"checkpoint": 2, "model": 2, "library": 4, "dataset": 4, "scene": 8192, "sha256": 65536}
DEFAULT_LIMIT = 16
#: Environment variable: ``0`` turns the tables off.
ENV = "SPREAD_READ_ONCE"

_TABLES: dict[str, OrderedDict] = {}
_LOCK = threading.RLock()
_READS: Counter = Counter()
_HITS: Counter = Counter()


def enabled() -> bool:
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "false", "no", "off")


def file_key(path: str | os.PathLike) -> tuple[str, int, int, int, int, int]:
    """(resolved path, device, inode, size in bytes, mtime in ns, ctime in ns) of a file (module docstring);
    ``OSError`` when it cannot be stat'ed."""
    p = Path(path).resolve()
    st = p.stat()
    return str(p), int(st.st_dev), int(st.st_ino), int(st.st_size), int(st.st_mtime_ns), int(st.st_ctime_ns)


def memo(kind: str, key: Hashable, load: Callable[[], object]):
    """``load()`` once per ``(kind, key)`` in this process (module docstring); later calls get the same object."""
    if not enabled():
        _READS[kind] += 1
        return load()
    with _LOCK:
        table = _TABLES.setdefault(kind, OrderedDict())
        if key in table:
            table.move_to_end(key)
            _HITS[kind] += 1
            return table[key]
        value = load()  # under the lock: two threads of one process never read the same file twice
        _READS[kind] += 1
        table[key] = value
        while len(table) > LIMITS.get(kind, DEFAULT_LIMIT):
            table.popitem(last=False)
        return value


def file_sha256(path: str | os.PathLike) -> str:
    """Hex sha256 of a regular file's bytes (:func:`spread.io.file_sha256`: a device or FIFO is refused)."""
    from spread.io import file_sha256 as sha256

    return memo("sha256", file_key(path), lambda: sha256(path))


def checkpoint(path: str | os.PathLike) -> dict:
    """A checkpoint's dict (:func:`spread.safe_load.load_checkpoint`: weights only, tensors memory-mapped on
    the CPU): the safety check, the hyperparameters and the weights all come from this one load."""
    from spread.safe_load import load_checkpoint

    if not Path(path).exists():  # the loader's message names a missing file
        return load_checkpoint(path, mmap=True)
    return memo("checkpoint", file_key(path), lambda: load_checkpoint(path, mmap=True))


def asset_library(root: str | os.PathLike):
    """The :class:`~spread.assets.AssetLibrary` of ``root`` (keyed by its ``index.json``)."""
    from spread.assets.library import AssetLibrary

    index = Path(root) / "index.json"
    if not index.exists():  # the loader names the missing index
        return AssetLibrary.load(root)
    return memo("library", file_key(index), lambda: AssetLibrary.load(Path(root).resolve()))


def library_key(library) -> tuple:
    """What a library was loaded from (its ``index.json``), for keys of entries validated against it."""
    root = getattr(library, "root", None)
    if root is None:
        return ("assets", id(library))
    try:
        return file_key(Path(root) / "index.json")
    except OSError:
        return (str(root), id(library))


def scene(path: str | os.PathLike, library=None):
    """The validated :class:`~spread.scene.Scene` of a scene file (:func:`spread.scene.read_scene` against
    ``library``); errors as ``read_scene``'s, never kept."""
    from spread.scene import read_scene

    try:
        key = (file_key(path), None if library is None else library_key(library))
    except OSError:  # missing or unreadable: read_scene names the problem
        return read_scene(path, assets=library)
    return memo("scene", key, lambda: read_scene(path, assets=library))


def counts() -> dict[str, dict[str, int]]:
    """``{kind: {"reads": n, "hits": m}}`` since the process started (or :func:`clear`)."""
    return {k: {"reads": _READS[k], "hits": _HITS[k]} for k in sorted(set(_READS) | set(_HITS))}


def clear() -> None:
    """Forget every entry and count (tests; a process that wants its memory back)."""
    with _LOCK:
        _TABLES.clear()
        _READS.clear()
        _HITS.clear()
