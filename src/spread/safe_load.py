"""The loader policy for files the platform did not write itself: no data file runs code.

* ``.npz`` arrays (scene files, asset caches, the release's ``boxes.npz``): :func:`load_npz`, numpy with
  ``allow_pickle=False`` — an object array (which numpy can only restore by unpickling) is refused with an
  error naming the file, never loaded.
* Checkpoints: :func:`load_checkpoint`, ``torch.load(weights_only=True)`` — tensors, containers and plain
  values only (what Lightning writes for the platform's modules: no allow-list is needed). A pickled
  object (a ``__reduce__`` payload, a custom class) is refused before anything in it runs; a truncated or
  corrupt file gets an error naming it instead of a bare ``PytorchStreamReader`` traceback.

Both raise :class:`UnsafeFileError` (a ``ValueError``) with the file and the reason.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path


class UnsafeFileError(ValueError):
    """A data file or checkpoint that cannot be loaded safely: it needs unpickling, or it is damaged."""


def file_kind(path: Path) -> str:
    """``zip`` for a zip archive, whole or torn (an ``.npz``, torch's checkpoint format); ``pickle`` for bytes that open as a pickle
    of protocol 2 or later (torch's legacy checkpoints; a ``.npy`` of objects); else what the file starts with, in
    words, for an error message (``a text file starting with '{"bounds'``, ``an empty file``)."""
    import zipfile

    with open(path, "rb") as f:
        head = f.read(16)
    if head[:2] == b"PK" or zipfile.is_zipfile(path):  # a torn zip too: its reader names what is wrong
        return "zip"
    if head[:1] == b"\x80":
        return "pickle"
    if not head:
        return "an empty file"
    try:
        return f"a text file starting with {head.decode('utf-8')!r}"
    except UnicodeDecodeError:
        return f"a file starting with bytes {head[:8]!r}"


def load_npz(path: str | os.PathLike):
    """``np.load(path, allow_pickle=False)`` (an ``NpzFile``; use it as a context manager). Reading an object
    array from it raises :class:`UnsafeFileError` naming the file and the key."""
    import numpy as np

    from spread.io import InputFileError, check_input_file

    path = Path(path)
    try:
        check_input_file(path)  # a regular file of plausible size: never a device or FIFO
    except InputFileError as exc:
        raise UnsafeFileError(str(exc)) from None
    kind = file_kind(path)
    if kind != "zip":  # numpy reads any other bytes as a pickle and calls the file "pickled (object) data"
        raise UnsafeFileError(f"{path}: not a readable .npz archive (a zip of .npy arrays): {kind}")
    data = np.load(path, allow_pickle=False)
    if not hasattr(data, "files"):
        data.close() if hasattr(data, "close") else None
        raise UnsafeFileError(f"{path}: not an .npz archive of arrays")
    problem = unpacked_size_problem(data, path)
    if problem:
        data.close()
        raise UnsafeFileError(problem)
    return _GuardedNpz(data, path)


def unpacked_size_problem(data, path: Path) -> str | None:
    """Why an opened ``.npz`` (``np.load``'s ``NpzFile``) is refused for its arrays' size once unpacked, or None: the
    limit on an input file (:func:`spread.io.max_input_bytes`) holds for the arrays as read, not only for the file
    on disk — ``np.savez_compressed`` packs 3 GB of zeros into 3 MB, which reading would unpack (a zip member's size
    as its header gives it; a member that unpacks past its header's size is cut there by ``zipfile``)."""
    from spread.io import MAX_INPUT_ENV, max_input_bytes

    limit = max_input_bytes()
    members = getattr(getattr(data, "zip", None), "infolist", None)
    if not limit or members is None:
        return None
    sizes = {info.filename.removesuffix(".npy"): int(info.file_size) for info in members()}
    total = sum(sizes.values())
    if total <= limit:
        return None
    key, largest = max(sizes.items(), key=lambda item: item[1])
    return (f"{path}: its arrays unpack to {total / 2 ** 20:.1f} MB (key '{key}': {largest / 2 ** 20:.1f} MB), over "
            f"the {limit / 2 ** 20:.0f} MB limit for one input file; set {MAX_INPUT_ENV}=<megabytes> to raise it "
            f"(0: no limit)")


class _GuardedNpz:
    """An ``NpzFile`` whose object arrays raise :class:`UnsafeFileError` (file and key) instead of numpy's
    bare "Object arrays cannot be loaded when allow_pickle=False"."""

    def __init__(self, data, path: Path):
        self._data, self.path = data, path
        self.files = list(data.files)

    def __getitem__(self, key: str):
        try:
            return self._data[key]
        except ValueError as exc:
            if "allow_pickle" in str(exc):
                raise UnsafeFileError(f"{self.path}: key '{key}' is an object array; reading it would unpickle "
                                      f"Python objects from the file, which the platform never does") from None
            raise

    def __contains__(self, key: str) -> bool:
        return key in self._data.files

    def keys(self):
        return self._data.files

    def get(self, key: str, default=None):
        return self[key] if key in self else default

    def close(self) -> None:
        self._data.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def load_checkpoint(path: str | os.PathLike, map_location="cpu", mmap: bool = False) -> dict:
    """A checkpoint's dict, loaded with ``weights_only=True`` (module docstring); ``mmap`` reads tensors
    lazily (cheap when only the hyperparameters are wanted; a file in torch's legacy, non-zip format is read whole,
    as it cannot be mapped)."""
    import torch

    from spread.io import InputFileError, check_input_file

    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise FileNotFoundError(f"{path}: no such checkpoint file")
    try:
        check_input_file(path, max_bytes=0)  # a regular file (checkpoints may be large: no size limit)
    except InputFileError as exc:
        raise UnsafeFileError(str(exc)) from None
    if mmap:
        import zipfile

        mmap = zipfile.is_zipfile(path)  # torch's legacy format (before 1.6, or saved without the zip) maps nothing
    kind = file_kind(path)
    if kind not in ("zip", "pickle"):  # torch read it as a pickle and it was called "pickled Python objects"
        raise UnsafeFileError(f"{path}: not a readable checkpoint (neither torch's zip format nor its legacy one): "
                              f"{kind}")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=True, mmap=mmap)
    except pickle.UnpicklingError as exc:
        detail = str(exc).strip().splitlines()[-1][:300] if str(exc).strip() else type(exc).__name__
        raise UnsafeFileError(f"{path}: refused — it holds pickled Python objects beyond tensors and plain data, "
                              f"which could run code when loaded ({detail})") from None
    except Exception as exc:  # noqa: BLE001 — torch's legacy reader fails on other bytes with IndexError, KeyError, …
        raise UnsafeFileError(f"{path}: not a readable checkpoint (truncated or corrupt: "
                              f"{type(exc).__name__}: {str(exc)[:200]})") from None
    if not isinstance(checkpoint, dict):
        raise UnsafeFileError(f"{path}: not a checkpoint (a {type(checkpoint).__name__}, expected a dict)")
    return checkpoint


class CheckpointMismatchError(ValueError):
    """A readable checkpoint that is not the one a command expects (another method, variant or network size);
    the message is one line: the file, what it holds, what was expected."""


def checkpoint_identity(checkpoint: dict) -> dict:
    """What a checkpoint holds, from its hyperparameters only: ``method`` (no key: ``spread``), ``variant``
    (SceneDiffusion's base / geometry) and the network sizes of its ``config`` (its integers)."""
    hp = checkpoint.get("hyper_parameters") or {}
    config = hp.get("config") if isinstance(hp.get("config"), dict) else {}
    return {"method": str(hp.get("method") or "spread"), "variant": hp.get("variant"),
            **{f"config.{k}": v for k, v in config.items() if isinstance(v, int) and not isinstance(v, bool)}}


def expect_checkpoint(path: str | os.PathLike, what: str, checkpoint: dict | None = None, **expected) -> dict:
    """The checkpoint at ``path`` (read with :func:`load_checkpoint`, tensors memory-mapped) once its
    :func:`checkpoint_identity` matches ``expected`` (keys ``method``, ``variant``, ``config.<size>``);
    :class:`CheckpointMismatchError` in one line otherwise, before any network is built. ``what`` names the
    setting that gave the file (``train.ckpt.geometry``)."""
    checkpoint = checkpoint if checkpoint is not None else load_checkpoint(path, mmap=True)
    held = checkpoint_identity(checkpoint)
    wrong = {k: v for k, v in expected.items() if v is not None and held.get(k) != v}
    if wrong:
        holds = ", ".join(f"{k}={held.get(k)!r}" for k in wrong)
        wants = ", ".join(f"{k}={v!r}" for k, v in wrong.items())
        kind = f"a '{held['method']}'" + (f" {held['variant']}" if held.get("variant") else "")
        raise CheckpointMismatchError(f"{what}={path}: {kind} checkpoint ({holds}); expected {wants}")
    return checkpoint
