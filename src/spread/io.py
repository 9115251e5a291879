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


def read_json_object(path: str | os.PathLike, error: type[Exception] = ValueError) -> dict:
    """The JSON object in file ``path``; ``error`` naming the file when it is not valid JSON or not an object
    (a missing file raises ``FileNotFoundError`` as ``open`` does: callers that explain it check first)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise error(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


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


#: Characters a :func:`safe_name` keeps as they are (portable file-name characters).
_SAFE_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-")
#: Longest name :func:`safe_name` returns (well below the 255-byte limit of common file systems, room
#: left for suffixes such as ``_k3.npz``).
SAFE_NAME_MAX = 120
_HASH_LEN = 10


def safe_name(text: str) -> str:
    """``text`` (any id: a dataset tag, an asset name) as one safe path component.

    A name made only of ``[A-Za-z0-9._-]``, not starting with ``.`` and at most :data:`SAFE_NAME_MAX`
    characters is returned unchanged (so ``safe_name`` is idempotent). Any other is *hashed*: unsafe
    characters become ``_``, it is cut to fit, and ``_`` plus the first 10 hex digits of its SHA-256 are
    appended (``"ProcTHOR-Test-196-room|4"`` → ``"ProcTHOR-Test-196-room_4_<hash>"``, ``"../x"`` →
    ``"_._x_<hash>"``). Two different ids give the same name only if one is a hashed name whose 40-bit
    hash suffix another id reproduces (a hash collision). The result never contains a path separator,
    is never ``.``/``..`` or empty, and is never hidden. File systems that ignore case can still
    confuse ids that differ only in case.
    """
    import hashlib

    text = str(text)
    if text and not text.startswith(".") and len(text) <= SAFE_NAME_MAX and all(c in _SAFE_CHARS for c in text):
        return text
    digest = hashlib.sha256(text.encode("utf-8", "surrogatepass")).hexdigest()[:_HASH_LEN]
    body = "".join(c if c in _SAFE_CHARS else "_" for c in text)
    if body.startswith("."):
        body = "_" + body[1:]
    body = body[:SAFE_NAME_MAX - _HASH_LEN - 1]
    return f"{body}_{digest}"
