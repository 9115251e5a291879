"""Atomic file writes shared by every part that writes to disk.

A write goes to a temporary file in the destination folder and is moved into place with
``os.replace``, so a reader sees either the old file or the complete new one, never a torn file,
and a crash mid-write loses nothing that was already there.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on clean exit rename it onto ``path``.

    ``suffix`` defaults to the destination's suffix so that libraries which pick a format from the
    file name (numpy, trimesh, PIL) write the right one.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix if suffix is not None else "".join(path.suffixes),
        dir=path.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    # mkstemp creates 0600; give the file the permissions a plain open() would (0666 minus umask)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp_path, 0o666 & ~umask)
    try:
        yield tmp_path
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, obj: Any, indent: int = 2) -> None:
    write_text_atomic(path, json.dumps(obj, indent=indent, sort_keys=False) + "\n")


def append_jsonl(path: str | os.PathLike, record: dict) -> None:
    """Append one JSON line and fsync it: a killed job keeps every line already appended.

    A torn last line (the process died mid-write) is skipped by :func:`read_jsonl`.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    line = json.dumps(record) + "\n"
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(line)
        fh.flush()
        os.fsync(fh.fileno())


def read_jsonl(path: str | os.PathLike) -> list[dict]:
    """Read a JSON-lines file, skipping a torn final line left by a killed writer."""
    path = Path(path)
    if not path.exists():
        return []
    out = []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            line = line.strip()
            if not line:
                continue
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                continue
    return out


def file_sha256(*paths: str | os.PathLike) -> str:
    """Hex SHA-256 of the files' bytes, concatenated in order (one file: its ordinary sha256)."""
    import hashlib

    h = hashlib.sha256()
    for p in paths:
        with open(p, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


#: Characters a :func:`safe_name` keeps as they are.
_SAFE_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-")
_WINDOWS_DEVICES = frozenset({"CON", "PRN", "AUX", "NUL", *(f"COM{i}" for i in range(10)),
                              *(f"LPT{i}" for i in range(10))})
#: Longest name :func:`safe_name` returns (well under every common file system's 255-byte limit).
SAFE_NAME_MAX = 120


def safe_name(text: object) -> str:
    """A file name for any id: one path component, never ``.``/``..``, hidden or empty, on any file system.

    ``text`` (anything; ``str()`` of it) keeps its ASCII letters, digits, ``.``, ``_`` and ``-``; every other
    character becomes ``_`` and leading dots are dropped. When that changed anything, the result would be
    longer than :data:`SAFE_NAME_MAX`, or it is a Windows device name (``CON``, ``nul.txt``), 10 hex digits of the id's SHA-256 are appended (``-<hash>``), so two
    different ids never share a name (``room|4`` → ``room_4-<hash>``, distinct from the id ``room_4``).
    Deterministic: the same id always gives the same name.
    """
    import hashlib

    raw = str(text)
    kept = "".join(c if c in _SAFE_CHARS else "_" for c in raw).lstrip(".")
    reserved = kept.split(".")[0].upper() in _WINDOWS_DEVICES
    if kept == raw and 0 < len(kept) <= SAFE_NAME_MAX and not reserved:
        return kept
    digest = hashlib.sha256(raw.encode("utf-8", "surrogatepass")).hexdigest()[:10]
    return f"{kept[:SAFE_NAME_MAX - 11]}-{digest}" if kept else f"id-{digest}"
