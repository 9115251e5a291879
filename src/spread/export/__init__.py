"""Simulation-ready export of scenes (``spread-export``): URDF (pybullet), MJCF (MuJoCo), USD (Isaac Sim), glb.

Every format carries what a simulator needs: the visual mesh, the collision parts (the asset's exact convex
parts, the same bodies as the platform's Stability worlds), mass, centre of mass and inertia, and a static
floor whose top is y = 0 (MJCF: z = 0, see below). Per scene, under ``out_dir``:

=======  ======================================  ===================================================
format   written                                 loads with
=======  ======================================  ===================================================
urdf     ``<id>/scene.json`` + URDFs + .obj      :func:`spread.export.urdf.load_urdf_scene` (pybullet)
mjcf     ``<id>.xml`` (self-contained)           ``mujoco.MjModel.from_xml_path``; z-up (y-up room
                                                 turned by a ``<frame>``), gravity −z
usd      ``<id>.usda``                           ``pxr.Usd.Stage.Open``; Isaac Sim; y-up stage
glb      ``<id>.glb``                            viewers (no physics data)
sceneeval ``<id>/scene_state.json`` + .obj       SceneEval (3dlg-hcvc/SceneEval): its scene-state
                                                 format, z-up (:mod:`spread.export.sceneeval`)
=======  ======================================  ===================================================

``<id>`` is :func:`spread.io.safe_name` of the scene id: one path component whatever the id holds, so
nothing is written outside ``out_dir``. Writes are atomic: a file goes through a temporary file and a
rename; a URDF folder is built in a temporary folder beside it and renamed into place.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import traceback
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import MISSING

FORMATS = ("urdf", "mjcf", "usd", "glb", "sceneeval")


@dataclass
class ExportConfig:
    """``spread-export``: scenes: folder of ``<scene_id>.npz`` files; out_dir: files go here, one per scene;
    assets: the asset library folder (None: the ``assets/`` folder beside ``scenes`` or inside it); format:
    one of :data:`FORMATS`; floor: a static floor (top face at y = 0); progress: a tqdm bar."""

    scenes: str = MISSING
    out_dir: str = MISSING
    assets: str | None = None
    format: str = "urdf"
    floor: bool = True
    progress: bool = True


def assets_of(scenes: str | os.PathLike, assets: str | os.PathLike | None) -> Path:
    """The asset library folder: ``assets`` if given, else ``assets/`` beside the scenes folder or inside it, else
    that of the dataset a sampling run's scenes came from (:func:`sampled_from`)."""
    if assets:
        path = Path(assets)
        if not (path / "index.json").exists():
            raise FileNotFoundError(f"assets={assets}: not an asset library (no index.json)")
        return path
    for candidate in (Path(scenes).parent / "assets", Path(scenes) / "assets"):
        if (candidate / "index.json").exists():
            return candidate
    try:
        recorded, why = sampled_from(scenes), ""
    except ValueError as exc:  # a damaged record: said with the refusal, which asks for assets=
        recorded, why = None, f"; {exc}"
    if recorded is not None and (recorded / "index.json").exists():
        return recorded
    raise FileNotFoundError(f"no asset library beside scenes={scenes} (looked for ../assets, assets/ and the dataset "
                            f"a sampling run's sampling.json names{why}); give assets=DIR")


def sampled_from(scenes) -> Path | None:
    """``<data_root>/assets`` of the dataset a sampling run's scenes were sampled from (``../sampling.json``'s
    ``fingerprint.data_root``, read by :func:`spread.io.sampled_data`, where its asset library is); None for scenes
    of no sampling run or a record that names no dataset; ``ValueError`` naming the file and key for a damaged
    record."""
    from spread.io import sampled_data

    record = Path(scenes).parent / "sampling.json"
    if Path(scenes).name != "scenes" or not record.is_file():
        return None
    root, _ = sampled_data(record)
    return root / "assets" if root is not None else None


SUFFIX = {"urdf": "", "mjcf": ".xml", "usd": ".usda", "glb": ".glb", "sceneeval": ""}


def scene_colours(scene, palette: str | None = None) -> np.ndarray:
    """(N, 4) RGBA in [0, 1]: each object's category colour (the render palette)."""
    from spread.render.palette import DEFAULT_PALETTE, category_colour

    rgb = [category_colour(str(c), palette or DEFAULT_PALETTE) for c in scene.category]
    return np.concatenate([np.asarray(rgb, np.float64).reshape(-1, 3) / 255.0, np.ones((len(rgb), 1))], axis=1)


def export_path(out_dir: str | os.PathLike, scene_id: str, fmt: str) -> Path:
    """Where ``scene_id`` is written in ``fmt`` under ``out_dir`` (always a direct child of ``out_dir``)."""
    from spread.io import safe_name

    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r} (known: {', '.join(FORMATS)})")
    out = Path(out_dir).resolve()
    path = out / (safe_name(scene_id) + SUFFIX[fmt])
    if path.parent != out:  # safe_name returns one path component; this guards the guarantee
        raise ValueError(f"export path {path} of scene id {scene_id!r} is not inside {out}")
    return path


def export_scene(scene, library, out_dir: str | os.PathLike, fmt: str, floor: bool = True) -> Path:
    """Write ``scene`` in ``fmt`` under ``out_dir`` (module docstring); returns the file or folder written."""
    path = export_path(out_dir, scene.scene_id, fmt)
    path.parent.mkdir(parents=True, exist_ok=True)
    colours = scene_colours(scene)
    if fmt == "urdf":
        from spread.export.urdf import write_urdf_scene

        _write_folder(path, lambda tmp: write_urdf_scene(scene, library, tmp, colours, floor=floor))
    elif fmt == "mjcf":
        from spread.io import safe_name, write_text_atomic
        from spread.physics.mjcf import scene_mjcf

        names = [f"o{i:03d}_{safe_name(a)}" for i, a in enumerate(scene.asset_id)]
        write_text_atomic(path, scene_mjcf(scene, library, up="z", visual=True, floor=floor, names=names,
                                           colours=colours))
    elif fmt == "usd":
        from spread.export.urdf import floor_rect
        from spread.export.usd import build_usd_stage
        from spread.io import atomic_path

        with atomic_path(path) as tmp:
            tmp.unlink()  # pxr creates the layer itself (and refuses an existing file)
            build_usd_stage(scene, library, tmp, colours, floor=floor, floor_rect=floor_rect(scene))
    elif fmt == "sceneeval":
        from spread.export.sceneeval import write_sceneeval_scene

        _write_folder(path, lambda tmp: write_sceneeval_scene(scene, library, tmp))
    else:
        from spread.render.export import export_glb

        export_glb(scene, library, path, floor=floor)
    return path


def _write_folder(path: Path, fill) -> None:
    """Build a folder with ``fill(tmp_folder)`` beside ``path``, then move it into place (replacing an older one)."""
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", dir=path.parent))
    try:
        fill(tmp)
        os.chmod(tmp, 0o777 & ~_umask())
        if path.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old.", dir=path.parent))
            os.replace(path, old / "x")
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@dataclass
class ExportReport:
    """What :func:`export_folder` did: files written (by scene id) and scenes that failed (id → error). A scene
    whose id another file of the folder already has, or whose output would replace something ``out_dir`` held that no
    export there wrote, is exported as ``<id>__<its file stem>`` and listed in ``duplicates`` (no output overwrites
    another, or what is not an export's)."""

    format: str
    out_dir: str
    written: dict[str, str] = field(default_factory=dict)
    failed: dict[str, str] = field(default_factory=dict)
    sources: dict[str, str] = field(default_factory=dict)  # exported id → its scene file
    duplicates: dict[str, str] = field(default_factory=dict)  # scene file → why and under which id it was exported
    removed_stale: list[str] = field(default_factory=list)  # outputs of the export before that this one did not write

    def to_dict(self) -> dict:
        return {"format": self.format, "out_dir": self.out_dir, "n_written": len(self.written),
                "n_failed": len(self.failed), "written": self.written, "failed": self.failed,
                "duplicates": self.duplicates, "removed_stale": self.removed_stale}


def earlier_outputs(out_dir) -> dict[str, str]:
    """The outputs the folder's previous ``export.json`` lists (output name → its scene id): only a direct child of
    ``out_dir`` named as the export names its scene's output (:func:`export_path`) and not one of :data:`OWN_FILES`,
    whatever the old report says; none without a readable report."""
    from spread.io import read_json

    out = Path(out_dir).resolve()
    try:
        before = read_json(out / "export.json")
    except (OSError, ValueError):
        return {}
    listed = before.get("written") if isinstance(before, dict) else None
    fmt = before.get("format") if isinstance(before, dict) else None
    if not isinstance(listed, dict) or fmt not in FORMATS:
        return {}
    outputs = {}
    for scene_id, old in listed.items():
        name = Path(str(old)).name
        if Path(str(old)).parent == out and name == export_path(out, str(scene_id), fmt).name and name not in OWN_FILES:
            outputs[name] = str(scene_id)
    return outputs


def remove_stale_exports(out_dir, written: dict[str, str], earlier: dict[str, str] | None = None) -> list[str]:
    """Remove the outputs the folder's previous ``export.json`` lists (``earlier``, as :func:`earlier_outputs` read it
    before this export began; None: read it now) that this export did not write (a scene removed, renamed or failing
    now, another format): the folder then holds what its ``export.json`` lists. Returns the names removed."""
    import shutil

    out = Path(out_dir).resolve()
    kept = {Path(p).name for p in written.values()}
    removed = []
    for name in earlier_outputs(out) if earlier is None else earlier:
        path = out / name
        if name in kept or not os.path.lexists(path):
            continue
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
        removed.append(name)
    return sorted(removed)


#: The export command's own files in its output folder, which no scene's output may take.
OWN_FILES = ("export.json", "export.log")


def output_clash(scene_id: str, taken: dict[str, str], out_dir, fmt: str, earlier: dict | None = None) -> str | None:
    """Why ``scene_id``'s output cannot be written as named — its output name is one of :data:`OWN_FILES`, in
    ``taken`` (output name → the scene file written under it by this export), or (given ``earlier``, the outputs of
    the folder's earlier exports: :func:`earlier_outputs`) a file or folder ``out_dir`` holds that no earlier export
    there wrote (a dataset's ``assets/``, a user's file: never replaced) — or None."""
    path = export_path(out_dir, scene_id, fmt)
    if path.name in OWN_FILES:
        return f"names the export's own {path.name}"
    if path.name in taken:
        return f"gives the output name of {taken[path.name]}"
    if earlier is not None and path.name not in earlier and os.path.lexists(path):
        return f"gives the output name of {path.name}, which out_dir held before and no export there wrote"
    return None


def free_id(wanted: str, taken: dict[str, str], out_dir, fmt: str, earlier: dict | None = None) -> str:
    """``wanted``, or ``wanted_2``, ``wanted_3``, ...: the first id whose output clashes with nothing
    (:func:`output_clash`)."""
    candidate, n = wanted, 1
    while output_clash(candidate, taken, out_dir, fmt, earlier):
        n += 1
        candidate = f"{wanted}_{n}"
    return candidate


def note_progress(out_dir, fmt: str, earlier: dict[str, str], written: dict[str, str]) -> None:
    """``export.json`` while an export runs (atomic, after each scene): the earlier export's outputs of this format
    and this one's so far, so a relaunch after a kill finds the outputs written before it as an export's own
    (:func:`earlier_outputs`: replaced, not exported again under another name); the finished report replaces it."""
    from spread.io import write_json_atomic

    out = Path(out_dir).resolve()
    listed = {sid: str(out / name) for name, sid in earlier.items() if export_path(out, sid, fmt).name == name}
    write_json_atomic(out / "export.json", {"format": fmt, "out_dir": str(out), "in_progress": True,
                                             "written": {**listed, **written}})


def export_folder(scenes: str | os.PathLike, assets: str | os.PathLike, out_dir: str | os.PathLike, fmt: str,
                  floor: bool = True, progress: bool = False) -> ExportReport:
    """Export every scene file of ``scenes`` (asset library ``assets``) in ``fmt`` to ``out_dir``.

    A scene that cannot be read or exported is reported in ``failed`` (its file and the error) and the others
    go on. The outputs of an export before into ``out_dir`` that this one did not write are removed
    (:func:`remove_stale_exports`); ``out_dir/export.json`` (atomic) records the report.
    """
    from spread.assets import AssetLibrary
    from spread.io import write_json_atomic
    from spread.scene import list_scene_files, read_scene

    if fmt not in FORMATS:
        raise ValueError(f"format={fmt!r}: unknown export format (known: {', '.join(FORMATS)})")
    library = AssetLibrary.load(assets)
    files = list_scene_files(scenes)
    report = ExportReport(fmt, str(Path(out_dir).resolve()))
    iterator = files
    if progress:
        from tqdm import tqdm

        iterator = tqdm(files, desc=f"export {fmt}", unit="scene")
    taken: dict[str, str] = {}  # output name → the scene file written under it (renamed ids included)
    earlier = earlier_outputs(out_dir)  # what this command may replace: its own earlier outputs only
    for path in iterator:
        try:
            scene = read_scene(path, assets=library)
            clash = output_clash(str(scene.scene_id), taken, out_dir, fmt, earlier)
            if clash:  # outputs are named by id: this one would overwrite another output, the report or a stranger
                renamed = free_id(f"{scene.scene_id}__{path.stem}", taken, out_dir, fmt, earlier)
                report.duplicates[str(path)] = f"scene id '{scene.scene_id}' {clash}; exported as '{renamed}'"
                scene.scene_id = renamed
            written = export_scene(scene, library, out_dir, fmt, floor=floor)
            report.written[str(scene.scene_id)] = str(written)
            report.sources[str(scene.scene_id)] = str(path)
            taken[Path(written).name] = str(path)
            note_progress(out_dir, fmt, earlier, report.written)  # a killed export's outputs stay its own
        except Exception as exc:  # one bad scene does not stop the export
            report.failed[path.stem] = f"{path}: {type(exc).__name__}: {exc}"
            if os.environ.get("SPREAD_DEBUG"):
                traceback.print_exc()
    report.removed_stale = remove_stale_exports(out_dir, report.written, earlier)
    write_json_atomic(Path(out_dir) / "export.json", report.to_dict())
    return report
