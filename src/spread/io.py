"""Atomic file writes shared by every part that writes to disk, and the checks on what is read and written.

A write goes to a temporary file in the destination folder and is moved into place with
``os.replace``, so a reader sees either the old file or the complete new one, never a torn file,
and a crash mid-write loses nothing that was already there. Appends never follow a symbolic link
(:func:`open_append_nofollow`); an input is checked to be a regular file of plausible size before it is
read or hashed (:func:`check_input_file`); a run folder is locked while a run writes it (:func:`run_lock`).
"""

from __future__ import annotations

import contextlib
import json
import logging
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
    if path.exists() or path.is_symlink():  # a device, FIFO or oversized file is refused, not read
        try:
            check_input_file(path)
        except InputFileError as exc:
            raise error(str(exc)) from None
    try:
        data = json.loads(decoded(path.read_bytes(), path))
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc})") from exc
    except NotUtf8 as exc:
        raise error(str(exc)) from None
    except RecursionError:  # 100,000 nested brackets: Python's parser gives up (a traceback)
        raise error(f"{path}: not valid JSON (nested deeper than Python's parser reads)") from None
    if not isinstance(data, dict):
        raise error(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def append_jsonl(path: str | os.PathLike, record: dict) -> None:
    """Append one JSON line and fsync it: a killed job keeps every line already appended.

    A torn last line (the process died mid-write) is skipped by :func:`read_jsonl`. The file is opened
    without following a symbolic link (``O_NOFOLLOW``): a link planted at ``path`` is refused naming it, and
    the file it points to is never written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    line = json.dumps(record) + "\n"
    fd = open_append_nofollow(path)
    with os.fdopen(fd, "a", encoding="utf-8") as fh:
        fh.write(line)
        fh.flush()
        os.fsync(fh.fileno())


class UnsafeOutputError(OSError):
    """An output path that is not the platform's to write: a symbolic link, a device, a FIFO."""


def open_append_nofollow(path: str | os.PathLike) -> int:
    """A file descriptor of ``path`` opened for appending (created 0666 − umask when absent), never through a
    symbolic link and never a device or FIFO: :class:`UnsafeOutputError` naming the file otherwise."""
    path = Path(path)
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as exc:
        if path.is_symlink():
            raise UnsafeOutputError(f"{path}: a symbolic link (to {os.readlink(path)}); the platform writes its "
                                    f"run files only as plain files inside the run folder: remove the link") from None
        raise
    import stat

    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise UnsafeOutputError(f"{path}: not a regular file; the platform appends only to plain files")
    os.set_blocking(fd, True)
    return fd


def read_jsonl(path: str | os.PathLike) -> list[dict]:
    """Read a JSON-lines file, skipping a torn final line left by a killed writer (a regular file: a FIFO or
    device is refused by :func:`check_input_file`, without a size limit)."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        return []
    check_input_file(path, max_bytes=0)
    out = []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            line = line.strip()
            if not line:
                continue
            try:
                out.append(json.loads(line))
            except (json.JSONDecodeError, RecursionError):  # a torn line, or one nested past the parser: skipped
                continue
    return out


def file_sha256(*paths: str | os.PathLike) -> str:
    """Hex SHA-256 of the files' bytes, concatenated in order (one file: its ordinary sha256). Each must be a
    regular file (:func:`check_input_file` without a size limit): a device or FIFO is refused, not read."""
    import hashlib

    h = hashlib.sha256()
    for p in paths:
        check_input_file(p, max_bytes=0)
        with open(p, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


class InputFileError(ValueError):
    """An input that is not safe to read: not a regular file (a device, a FIFO, a folder), a symbolic link
    that leaves its folder, or larger than the per-file limit. The message names the file and the way out."""


#: Environment variable that overrides :data:`DEFAULT_MAX_INPUT_MB` (megabytes; 0 or less: no limit).
MAX_INPUT_ENV = "SPREAD_MAX_INPUT_MB"
#: Largest input file (scene ``.npz``, graph) read by default, in MB: a scene of a few hundred objects is
#: well under 1 MB, so this leaves room for large scenes with precomputed extras.
DEFAULT_MAX_INPUT_MB = 256.0


def max_input_bytes() -> int:
    """The per-file size limit in bytes (:data:`MAX_INPUT_ENV`, else :data:`DEFAULT_MAX_INPUT_MB`); 0: none (the
    variable is 0, negative or ``inf``)."""
    import math

    raw = os.environ.get(MAX_INPUT_ENV, "").strip()
    try:
        mb = float(raw) if raw else DEFAULT_MAX_INPUT_MB
    except ValueError:
        raise InputFileError(f"{MAX_INPUT_ENV}={raw!r}: not a number of megabytes") from None
    if math.isnan(mb):
        raise InputFileError(f"{MAX_INPUT_ENV}={raw!r}: not a number of megabytes")
    return int(mb * 2 ** 20) if 0 < mb < math.inf else 0


def _kind(mode: int) -> str:
    import stat

    for test, name in ((stat.S_ISDIR, "folder"), (stat.S_ISCHR, "character device"),
                       (stat.S_ISBLK, "block device"), (stat.S_ISFIFO, "FIFO (named pipe)"),
                       (stat.S_ISSOCK, "socket")):
        if test(mode):
            return name
    return "special file"


def check_input_file(path: str | os.PathLike, root: str | os.PathLike | None = None,
                     max_bytes: int | None = None) -> Path:
    """``path`` once it is safe to read, else :class:`InputFileError` naming it (before anything is opened,
    so a FIFO or ``/dev/zero`` never blocks or streams):

    * it exists and is a regular file (a symbolic link to one counts, see ``root``);
    * a symbolic link must resolve inside ``root`` (a folder; None: no containment check), so a link in a
      scenes folder cannot pull in ``/dev/zero`` or a file of another tree;
    * its size is at most ``max_bytes`` (None: :func:`max_input_bytes`; 0: no limit).
    """
    import stat

    path = Path(path)
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        raise InputFileError(f"{path}: file does not exist") from None
    if stat.S_ISLNK(st.st_mode):
        target = path.resolve()
        if root is not None and not target.is_relative_to(Path(root).resolve()):
            raise InputFileError(f"{path}: a symbolic link to {target}, outside {root}; refused (copy the file "
                                 f"into the folder instead of linking it)")
        try:
            st = os.stat(path)
        except OSError as exc:
            raise InputFileError(f"{path}: a broken symbolic link ({exc.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise InputFileError(f"{path}: not a regular file (a {_kind(st.st_mode)}); refused")
    limit = max_input_bytes() if max_bytes is None else int(max_bytes)
    if limit > 0 and st.st_size > limit:
        raise InputFileError(f"{path}: {st.st_size / 2 ** 20:.1f} MB, over the {limit / 2 ** 20:.0f} MB limit for "
                             f"one input file; set {MAX_INPUT_ENV}=<megabytes> to raise it (0: no limit)")
    return path


def decoded(data: bytes, path) -> str:
    """``data`` (the bytes of file ``path``) as UTF-8 text, a byte-order mark dropped (spreadsheets write one);
    not UTF-8: :class:`NotUtf8` (a ``ValueError``) naming the file and the byte."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise NotUtf8(f"{path}: not UTF-8 text (byte {exc.start}: {exc.object[exc.start:exc.start + 1]!r})") from None


class NotUtf8(ValueError):
    """A text file that is not UTF-8 (:func:`decoded`)."""


def read_text_checked(path: str | os.PathLike, root: str | os.PathLike | None = None,
                      max_bytes: int | None = None) -> str:
    """The UTF-8 text of ``path`` once :func:`check_input_file` passed it (the one door every reader of a run's
    or a user's text file goes through: a FIFO, a device or a link out of ``root`` is refused, never opened); a
    leading byte-order mark dropped; not UTF-8: a ``ValueError`` naming the file (:func:`decoded`)."""
    return decoded(Path(check_input_file(path, root, max_bytes)).read_bytes(), path)


def read_bytes_checked(path: str | os.PathLike, root: str | os.PathLike | None = None,
                       max_bytes: int | None = None) -> bytes:
    """The bytes of ``path`` once :func:`check_input_file` passed it."""
    return Path(check_input_file(path, root, max_bytes)).read_bytes()


def read_json(path: str | os.PathLike, root: str | os.PathLike | None = None):
    """The JSON value in ``path`` once :func:`check_input_file` passed it (``ValueError`` naming the file when it
    is not JSON; a missing file raises ``FileNotFoundError`` as ``open`` does)."""
    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise FileNotFoundError(f"{path}: no such file")
    try:
        return json.loads(read_text_checked(path, root))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None
    except RecursionError:  # 100,000 nested brackets: Python's parser gives up (a traceback)
        raise ValueError(f"{path}: not valid JSON (nested deeper than Python's parser reads)") from None


#: Characters a :func:`safe_name` keeps as they are (portable file-name characters).
_SAFE_CHARS = frozenset("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789._-")
#: Longest name :func:`safe_name` returns (well below the 255-byte limit of common file systems, room
#: left for suffixes such as ``_k3.npz``).
SAFE_NAME_MAX = 120
_HASH_LEN = 10


def sampled_data(record: str | os.PathLike) -> tuple[Path | None, str | None]:
    """(the dataset folder, the split) a sampling run's ``sampling.json`` at ``record`` names
    (``fingerprint.data_root``, ``fingerprint.split``), each None when not given: the one reader of where a run's
    scenes were sampled from (``spread-view``'s ground truth, ``spread-export``'s asset library). ``ValueError``
    naming the file and the key when the file is not JSON or a value is not what a sampling run writes (a split
    that is not one plain folder name: never a path out of the dataset)."""
    record = Path(record)
    fingerprint = read_json_object(record).get("fingerprint")
    if fingerprint is None:
        return None, None
    if not isinstance(fingerprint, dict):
        raise ValueError(f"{record}: 'fingerprint' holds {type(fingerprint).__name__}, expected an object (data_root, "
                         f"split: where the ground truth is); not a sampling run's record")
    values = {}
    for key in ("data_root", "split"):
        value = fingerprint.get(key)
        if value is not None and not isinstance(value, str):
            raise ValueError(f"{record}: 'fingerprint.{key}' holds {type(value).__name__} {value!r}, expected a "
                             f"{'folder path' if key == 'data_root' else 'split name'} (text)")
        values[key] = value or None
    split, root = values["split"], values["data_root"]
    if split is not None and safe_name(split) != split:
        raise ValueError(f"{record}: 'fingerprint.split' holds {split!r}, expected a split folder's name (train, val, "
                         f"test)")
    if root is not None and "\0" in root:
        raise ValueError(f"{record}: 'fingerprint.data_root' holds {root!r}, not a folder path")
    return (Path(root) if root else None), split


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


def refuse_links(*paths: str | os.PathLike) -> None:
    """Before a run writes its files: :class:`UnsafeOutputError` naming the first of ``paths`` that is a
    symbolic link (a link planted in a run folder would send the run's writes to its target)."""
    for path in paths:
        if Path(path).is_symlink():
            raise UnsafeOutputError(f"{path}: a symbolic link (to {os.readlink(path)}); the platform writes its run "
                                    f"files only as plain files inside the run folder: remove the link")


def planted_link(folder: str | os.PathLike) -> str | None:
    """Why a run folder cannot be written, for a symbolic link among its entries (the first by name), or None. The
    platform makes none there; a link planted at ``scenes``, ``renders``, ``checkpoints``, ``logs`` or ``.hydra``
    sent a run's writes, and its removal of stale results, to the link's target (``spread-sample`` deleted the
    files of the folder ``scenes`` led to and wrote its own there). Link the run folder itself instead."""
    try:
        entries = sorted(os.scandir(folder), key=lambda e: e.name)
    except (FileNotFoundError, NotADirectoryError):
        return None
    for entry in entries:
        if entry.is_symlink():
            return (f"{Path(folder) / entry.name}: a symbolic link (to {os.readlink(entry.path)}) inside the run "
                    f"folder; the run would write and delete its files through it: remove the link (a run folder "
                    f"may itself be a link, its entries not)")
    return None


class RunLogFileHandler(logging.FileHandler):
    """Hydra's ``<command>.log`` handler (``conf/hydra/default.yaml``): a symbolic link planted at the log's
    path is replaced by a plain file (its target is never opened), and the file is opened with ``O_NOFOLLOW``."""

    def _open(self):
        path = Path(self.baseFilename)
        if path.is_symlink():
            path.unlink()
        fd = open_append_nofollow(path) if "a" in self.mode else os.open(
            path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_NOFOLLOW", 0), 0o666)
        return os.fdopen(fd, self.mode, encoding=self.encoding, errors=self.errors)


class RunFolderBusy(RuntimeError):
    """A run folder another live run is writing (its lock is held); the message names the folder and the run."""


#: The lock file of a run folder (:func:`run_lock`).
LOCK_FILE = ".spread.lock"


#: What marks a folder as a command's: (kind, the file or folder that says so). A command refuses an ``out_dir`` that
#: holds another kind (:func:`check_folder_kind`).
FOLDER_MARKS = (("dataset", "assets/index.json"), ("training run", "checkpoints"), ("sampling run", "sampling.json"),
                ("evaluation", "protocol.json"), ("export", "export.json"), ("ablation", "ablation.json"),
                ("comparison", "compare.json"), ("sweep", "points"), ("report", "report.json"))


def folder_kinds(folder: str | os.PathLike) -> dict[str, str]:
    """The kinds of run or dataset ``folder`` holds (:data:`FOLDER_MARKS`), each with the path that says so."""
    folder = Path(folder)
    return {kind: str(folder / mark) for kind, mark in FOLDER_MARKS if (folder / mark).exists()}


#: What confirms, for a folder ABOVE an ``out_dir``, the kinds :func:`enclosing_folder` refuses: the
#: :data:`FOLDER_MARKS` mark and one of these records the platform writes there (a home folder holding an unrelated
#: ``checkpoints/`` or ``assets/index.json`` is no run or dataset, and whatever lies under it stays accepted).
ENCLOSING_MARKS = {"dataset": ("stats.json", "manifest.json", "generation.json"),
                   "training run": ("clock.jsonl", "metrics.json", ".hydra/config.yaml")}

#: A dataset's own parts (asset library, split folders, its renders and Hydra logs): never an export's ``out_dir``.
DATASET_PARTS = frozenset({"assets", "train", "val", "test", "renders", "logs"})

#: How many folders above an ``out_dir`` :func:`enclosing_folder` looks at (the filesystem root comes first).
ENCLOSING_DEPTH = 64


def _kind_here(folder: Path, kind: str) -> str | None:
    """``folder``'s mark of ``kind`` (:data:`FOLDER_MARKS`) when one of its records (:data:`ENCLOSING_MARKS`) confirms
    it, else None."""
    mark = folder / dict(FOLDER_MARKS)[kind]
    if not mark.exists() or not any((folder / record).exists() for record in ENCLOSING_MARKS[kind]):
        return None
    return str(mark)


def _dataset_part(dataset: Path, out: Path) -> bool:
    """Whether ``out`` (inside ``dataset``) lies in one of the dataset's own parts: :data:`DATASET_PARTS`, or a folder
    directly in it that holds scene files (a split of another name)."""
    first = dataset / out.relative_to(dataset).parts[0]
    if first.name in DATASET_PARTS:
        return True
    try:
        with os.scandir(first) as entries:
            return any(e.name.endswith(".npz") for e in entries)
    except OSError:  # not there yet, or no folder
        return False


def enclosing_folder(folder: str | os.PathLike, command: str) -> tuple[Path, str, str] | None:
    """The folder above ``folder`` (a command's ``out_dir``, resolved: links followed) that the command must not write
    inside, as (folder, kind, the mark that says so); None when there is none. The rule:

    * a **dataset** (``assets/index.json`` with ``stats.json``, ``manifest.json`` or ``generation.json``): no
      ``out_dir`` strictly inside it, at any depth (a training run in ``<dataset>/train`` put its checkpoints among
      the scene files the next training reads; a run in ``<dataset>/assets`` sat in the asset library). The one
      nesting the platform documents: ``spread-export`` into a folder of its own in the dataset
      (``conf/export.yaml``: ``scenes=/tmp/rooms/test out_dir=/tmp/rooms/export_mjcf``), never inside the
      dataset's parts (:data:`DATASET_PARTS`, or a folder holding scene files);
    * a **training run** (``checkpoints/`` with ``clock.jsonl``, ``metrics.json`` or ``.hydra/config.yaml``): no
      ``out_dir`` strictly inside it (a dataset in a run's ``checkpoints/``; ``fresh=true`` moves the run's history
      to ``previous/<time>`` and leaves other commands' folders beside the new one), but for training's own layout:
      ``spread-train`` in ``<run>/previous/<name>`` (an earlier history ``fresh=true`` set aside);
    * every other kind of :data:`FOLDER_MARKS` takes runs inside it, as the platform lays them out: an evaluation or an
      export in a sampling run (``spread-evaluate scenes=<run>/scenes out_dir=<run>/eval``, ``spread-sample
      evaluate=true``), the runs and dataset of an ablation, comparison or sweep in its folder (``train/<variant>``,
      ``samples/<variant>``, ``points/<point>``, ``data/``), the runs under ``paths.runs_dir``.

    The walk stops at the filesystem root (at most :data:`ENCLOSING_DEPTH` folders) and costs a stat or two a folder.
    """
    out = Path(folder).resolve()
    for above in list(out.parents)[:ENCLOSING_DEPTH]:
        mark = _kind_here(above, "dataset")
        if mark is not None and not (command == "spread-export" and not _dataset_part(above, out)):
            return above, "dataset", mark
        mark = _kind_here(above, "training run")
        if mark is not None and not (command == "spread-train" and out.parent == above / "previous"):
            return above, "training run", mark
    return None


def check_folder_kind(folder: str | os.PathLike, command: str, allowed: set[str] | frozenset[str]) -> None:
    """``ValueError`` when ``folder`` (a command's ``out_dir``) holds a dataset or another command's run than the
    ``allowed`` kinds: an evaluation wrote over a training run's ``metrics.json``, a training run replaced a sampling
    run's recorded config, a sampling run wrote its scenes into a dataset folder. Also when ``folder`` lies inside a
    dataset or a training run (:func:`enclosing_folder`, which states the rule and the nestings the platform makes):
    a training run in ``<dataset>/train`` among the scene files, a dataset in ``<run>/checkpoints``."""
    foreign = {k: m for k, m in folder_kinds(folder).items() if k not in allowed}
    if foreign:
        kind, mark = next(iter(foreign.items()))
        article = "an" if kind[0] in "aeiou" else "a"
        raise ValueError(f"out_dir={folder}: holds {article} {kind} ({mark}); {command} would write over or beside it: "
                         f"give another out_dir")
    enclosing = enclosing_folder(folder, command)
    if enclosing:
        above, kind, mark = enclosing
        article = "an" if kind[0] in "aeiou" else "a"
        raise ValueError(f"out_dir={folder}: lies inside {article} {kind}, {above} ({mark}); {command} would write its "
                         f"files into it: give an out_dir outside {above}")


@contextlib.contextmanager
def run_lock(folder: str | os.PathLike, command: str, nest: bool = False) -> Iterator[Path]:
    """Hold ``folder``'s run lock while a run writes it: an exclusive ``flock`` on ``folder/.spread.lock``
    (released by the kernel when the process ends, so a killed run never leaves a stale lock). A second run
    on the same folder is refused within a moment (:func:`take_lock`) with :class:`RunFolderBusy` naming the holder
    (command, pid, start), so two runs never mix their files (two evaluations with other protocols sharing one
    ``metrics.json``).
    ``nest=True``: a run in this process that takes it again inside is part of this one (a command holds it
    before it opens its trackers, then calls the library run that takes it); any other hold is a second run."""
    import time

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK_FILE
    refuse_links(path)
    problem = planted_link(folder)
    if problem:
        raise UnsafeOutputError(problem)
    held = str(path.resolve())
    if _HELD_LOCKS.get(held):  # this process holds it for a run that nests this one (``nest``)
        yield path
        return
    fd = take_lock(folder, path)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{command} (pid {os.getpid()}, since {time.strftime('%Y-%m-%d %H:%M:%S')})\n".encode(), 0)
        _HELD_LOCKS[held] = nest
        try:
            yield path
        finally:
            _HELD_LOCKS.pop(held, None)
    finally:
        os.close(fd)  # closing the descriptor releases the lock


def take_lock(folder: Path, path: Path) -> int:
    """An open descriptor holding the exclusive ``flock`` on the file now at ``path`` (:func:`run_lock`). Locked again
    when the file it locked was removed meanwhile (a refused command removes the lock file it made while holding it,
    :func:`remove_held_lock`, and the folder it made: both are made again); a hold that outlasts a moment (a running
    run, not a refused one leaving) is :class:`RunFolderBusy` naming the holder."""
    import fcntl
    import stat
    import time

    busy = 0
    for _ in range(100):
        folder.mkdir(parents=True, exist_ok=True)
        made = not os.path.lexists(path)
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0),
                         0o666)
        except FileNotFoundError:  # the folder was removed after it was made again
            continue
        kept = False
        try:
            mode = os.fstat(fd).st_mode
            if not stat.S_ISREG(mode):
                raise UnsafeOutputError(f"{path}: the run folder's lock is not a regular file (a {_kind(mode)}); "
                                        f"remove it, the platform makes its own")
            os.set_blocking(fd, True)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip() or "another process"
                busy += 1
                if busy > 5:
                    raise RunFolderBusy(f"{folder}: in use by a running {holder}; wait for it to finish or use "
                                        f"another out_dir") from None
                time.sleep(0.05)  # a refused run removing its own lock holds it for a moment
                continue
            if same_file(fd, path):
                kept = True
                if made:
                    _MADE_LOCKS.add(normal_path(path))
                return fd
        finally:
            if not kept:
                os.close(fd)
    raise RunFolderBusy(f"{folder}: its run lock {path} keeps being replaced; is another process removing it?")


def remove_held_lock(path: Path) -> bool:
    """Remove the run-lock file ``path`` while holding its lock and only while it is the file at the path, so a run
    that holds it, or that made a new one since, is never left without its lock. Whether it was removed."""
    import fcntl

    try:
        fd = os.open(path, os.O_RDWR | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0))
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        if not same_file(fd, path):
            return False
        path.unlink()
        return True
    except OSError:  # BlockingIOError: another run holds it
        return False
    finally:
        os.close(fd)


def made_lock(path: Path) -> bool:
    """Whether this process made the run-lock file ``path`` when it took it (:func:`take_lock`)."""
    return normal_path(path) in _MADE_LOCKS


def normal_path(path: str | os.PathLike) -> Path:
    """``path`` as an absolute path without ``.`` or ``..`` parts, naming the folder the system means by it: a ``..``
    goes up from where the parts before it lead, links followed there (``link/../b`` is ``b`` beside the link's
    target, as ``mkdir`` makes it), other links not resolved (Hydra expands neither ``~`` nor ``..``)."""
    text = os.fspath(path)
    parts = Path(text if os.path.isabs(text) else os.path.join(os.getcwd(), text)).parts
    if ".." not in parts:
        return Path(os.path.normpath(os.path.join(*parts)))
    out = Path(parts[0])
    for part in parts[1:]:
        if part == "..":
            out = Path(os.path.realpath(out) if os.path.islink(out) else out).parent  # a missing ``a``: ``a/..`` is ``.``
        elif part != ".":
            out = out / part
    return out


def same_file(fd: int, path: Path) -> bool:
    """Whether the open file ``fd`` is still the file at ``path`` (not removed or replaced since it was opened)."""
    try:
        held, there = os.fstat(fd), os.stat(path, follow_symlinks=False)
    except FileNotFoundError:
        return False
    return (held.st_dev, held.st_ino) == (there.st_dev, there.st_ino)


#: The run locks this process holds (resolved lock-file path → whether a run inside may take it again: ``nest``).
_HELD_LOCKS: dict[str, bool] = {}
#: The run-lock files this process made (:func:`normal_path`), which a refused command may remove (cli.errors).
_MADE_LOCKS: set[Path] = set()
