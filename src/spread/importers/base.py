"""What every importer shares: room references, asset requests, the source interface, tag checks.

An importer (one module per source layout) turns a folder in someone else's layout into the platform's
dataset folder (DESIGN §4). It answers four questions, each for one room or one asset, so the driver
(:mod:`spread.importers.run`) can run them in parallel, resume, and count failures:

* :meth:`Source.rooms`: which rooms, in which split (and errors for entries that cannot be rooms);
* :meth:`Source.scan`: the assets a room needs (reads its file; errors name the file and key);
* :meth:`Source.import_asset`: one asset into the library (errors name the mesh file);
* :meth:`Source.scene`: the room as a :class:`~spread.scene.Scene` with the file's own graph, given the
  library (poses in the platform's frames: metres, y-up, floor y = 0, ``v_world = R · v_local + t``),
  and a dict of counts for the manifest.

Errors are exceptions whose message names the file and, where there is one, the key
(:class:`~spread.scene.SceneFormatError`, :class:`~spread.assets.mesh_files.MeshFileError`); the driver
records them per room or asset and goes on.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from spread.io import safe_name
from spread.scene import SceneFormatError

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class RoomRef:
    """One room of the source: its tag (the source's own id), split, and folder on disk."""

    tag: str
    split: str
    folder: str

    @property
    def scene_id(self) -> str:
        """The platform's scene id and file stem: :func:`spread.io.safe_name` of the tag."""
        return safe_name(self.tag)


@dataclass(frozen=True)
class AssetRequest:
    """An asset a room needs. kind "mesh": ``path`` (a mesh file), optionally scaled to ``size`` (3,)
    extents in metres; kind "box": an oriented box of extents ``size``."""

    asset_id: str
    category: str
    kind: str
    path: str | None = None
    size: tuple[float, float, float] | None = None


@dataclass
class RoomList:
    """What :meth:`Source.rooms` returns: the rooms, the entries that are not usable rooms (one error
    record each: tag, file, key, error), and how the splits were made (for the manifest)."""

    rooms: list[RoomRef]
    errors: list[dict] = field(default_factory=list)
    splits: dict = field(default_factory=dict)


class Source:
    """Interface of one source layout (module docstring). ``name`` is the ``source=`` value."""

    name = "?"

    def rooms(self) -> RoomList:  # pragma: no cover - interface
        raise NotImplementedError

    def scan(self, ref: RoomRef) -> list[AssetRequest]:  # pragma: no cover - interface
        raise NotImplementedError

    def import_asset(self, root: Path, request: AssetRequest, settings):  # pragma: no cover - interface
        """(AssetRecord, built?) of one request, written under the library ``root``."""
        from spread.assets.imported import import_box_asset, import_mesh_asset

        if request.kind == "box":
            return import_box_asset(root, request.asset_id, request.size, request.category, settings)
        return import_mesh_asset(root, request.asset_id, request.path, request.category, settings,
                                 scale_to=request.size)

    def scene(self, ref: RoomRef, library, requests: list[AssetRequest]):  # pragma: no cover - interface
        """(Scene, counts dict) of one room."""
        raise NotImplementedError

    def info(self) -> dict:
        """What the manifest records about the source (folders, options)."""
        return {}


def hash_fraction(tag: str) -> float:
    """A number in [0, 1) from the SHA-256 of ``tag``: an order-independent, reproducible draw."""
    import hashlib

    return int.from_bytes(hashlib.sha256(tag.encode("utf-8")).digest()[:8], "little") / 2.0 ** 64


def carve_val(train: list[str], fraction: float) -> set[str]:
    """The train tags that become val: the ``max(1, round(fraction · n))`` tags with the smallest
    :func:`hash_fraction` (none when train has fewer than two tags or ``fraction`` is 0)."""
    if len(train) < 2 or fraction <= 0:
        return set()
    k = min(len(train) - 1, max(1, int(round(fraction * len(train)))))
    return set(sorted(train, key=hash_fraction)[:k])


def check_tag(tag: object, src: Path, file: str, key: str) -> str:
    """``tag`` as a room folder name inside ``src``; raises :class:`SceneFormatError` naming ``file`` and
    ``key`` when it is not a string, is empty, ``.``/``..``, or holds a path separator (a hostile tag such
    as ``../x`` would read outside the source folder)."""
    if not isinstance(tag, str):
        raise SceneFormatError(file, key, f"tag {tag!r} is not a string")
    if tag in ("", ".", "..") or "/" in tag or "\\" in tag or "\x00" in tag or os.sep in tag:
        raise SceneFormatError(file, key, f"tag {tag!r} is not a single folder name (path separators and "
                                          f"'..' are refused: it would point outside {src})")
    resolved = (src / tag).resolve()
    if resolved.parent != src.resolve():
        raise SceneFormatError(file, key, f"tag {tag!r} resolves outside {src}")
    return tag


def within(path: Path, root: Path, file: str | None = None, key: str | None = None) -> Path:
    """``path`` once it lies inside ``root`` with every symbolic link along it followed (a linked room folder, a
    linked ``boxes.npz`` or mesh); else :class:`SceneFormatError` naming it (``file``/``key``: the room file and key
    that named it, when another file did). Links count only inside the input's folder (docs/robustness.md)."""
    real = Path(path).resolve()
    if not real.is_relative_to(Path(root).resolve()):
        named = f"{path} leads" if file else "leads"  # the error names its file first
        raise SceneFormatError(file or str(path), key, f"{named} to {real}, outside {root} through a symbolic link; "
                                                       f"refused (copy it into the folder instead of linking it)")
    return Path(path)


def error_record(tag: str | None, exc: BaseException, file: str | None = None) -> dict:
    """One failure as the manifest lists it: tag, file and key (when the error names them), message."""
    return {"tag": tag, "file": getattr(exc, "source", None) or getattr(exc, "path", None) or file,
            "key": getattr(exc, "key", None), "error": f"{type(exc).__name__}: {exc}"}
