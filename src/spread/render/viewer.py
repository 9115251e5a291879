"""``spread-view``: scenes in an interactive 3D viewer in the browser (viser; ``http://127.0.0.1:<port>/``).

What it shows, for the scene picked in the side panel:

* the scene's objects as their posed meshes (world frame, metres, y up), each coloured by its category (the
  render palette, :mod:`spread.render.palette`) with the legend in the panel;
* beside it (+x, one room width and 0.5 m further), the ground truth it was conditioned on, when known: a
  sampling run's scene names its graph (``conditioned_on``), found in the dataset's split folder
  (``sampling.json``: ``fingerprint.data_root``, ``split``);
* on request, the same scene after one Stability simulation (:func:`spread.render.physics_view.after_physics`),
  again beside it, with how far objects moved;
* the relation matrix of the scene (its graph's spatial codes against those of its poses,
  :func:`spread.render.figures.relation_matrix_figure`) and its GRecall;
* a timeline slider over the guidance iterations when the scene file carries them (extras
  ``trajectory_translation`` (T, N, 3) and ``trajectory_rotation`` (T, N, 3, 3)).

:func:`collect` reads what to show from a scene file, a folder of them, or a run folder (``scenes/``).

Every text the panel takes from data files (category names, scene ids, file names) is escaped first: the legend
is HTML (viser sets it as the element's inner HTML: :func:`html_text`), the scene's caption markdown
(:func:`markdown_text`), so a category ``<img src=x onerror=...>`` shows as those characters and runs nothing.
"""

from __future__ import annotations

import html
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from spread.render.palette import DEFAULT_PALETTE, category_colour

#: Gap (metres) between the scene and the copies shown beside it.
GAP = 0.5


@dataclass
class ViewItem:
    """One scene to show: its file and, when known, the ground-truth file it was conditioned on."""

    name: str
    path: Path
    ground_truth: Path | None = None


def html_text(text) -> str:
    """``text`` (from a data file) as HTML text: ``<``, ``>``, ``&`` and quotes as entities."""
    return html.escape(str(text), quote=True)


#: ASCII punctuation markdown may read as syntax (emphasis, links, code, tables, headings, MDX braces, math),
#: but ``&<>"'``, which :func:`html_text` turns into entities
MARKDOWN_SPECIALS = re.compile(r"""([!#$%()*+,\-./:;=?@\[\\\]^_`{|}~])""")


def markdown_text(text) -> str:
    """``text`` (from a data file) as literal markdown text on one line: every ASCII punctuation character markdown
    may read as syntax backslash-escaped (CommonMark), then HTML's specials as entities, so that no tag, link,
    emphasis or heading comes from it; line breaks and runs of white space become one space."""
    return html_text(MARKDOWN_SPECIALS.sub(r"\\\1", " ".join(str(text).split())))


def library_candidates(path: Path, data_root: Path | None) -> list[Path]:
    folder = path if path.is_dir() else path.parent
    out = [folder / "assets", folder.parent / "assets", folder.parent.parent / "assets"]
    if data_root is not None:
        out = [data_root / "assets", data_root.parent / "assets", *out]
    return out


def collect(path: str | os.PathLike, assets: str | os.PathLike | None = None,
            refused: list | None = None) -> tuple[list[ViewItem], Path]:
    """(the scenes to show, the asset library folder) of a scene file, a folder of scene files or a run
    folder; errors name the path. Every file goes through :func:`spread.io.check_input_file` before it is opened:
    a FIFO, a device or a link out of the folder among the scenes is left out and named in ``refused`` (a
    named file that is refused is an error)."""
    from spread.io import InputFileError, check_input_file
    from spread.scene import list_scene_files

    path = Path(path)
    if not path.exists() and not path.is_symlink():
        raise FileNotFoundError(f"spread-view: {path}: no such file or folder")
    data_root, split = None, None
    record = run_record(path)
    if record is not None:
        data_root, split = ground_truth_source(record)
    scenes_dir = path / "scenes" if (path / "scenes").is_dir() else path
    if not path.is_dir():
        try:
            files = [check_input_file(path)]
        except InputFileError as exc:
            raise InputFileError(f"spread-view: {exc}") from None
    else:
        files = []
        for f in list_scene_files(scenes_dir):
            try:
                files.append(check_input_file(f, root=scenes_dir))
            except InputFileError as exc:
                if refused is not None:
                    refused.append(str(exc))
    if not files:
        raise FileNotFoundError(f"spread-view: {path}: no readable scene files (.npz) here or in scenes/"
                                + (f" ({len(refused)} refused: {refused[0]})" if refused else ""))
    items = []
    for f in files:
        truth = None
        if data_root is not None and split:
            truth = data_root / split / f"{ground_truth_id(f)}.npz"
        items.append(ViewItem(f.stem, f, truth if truth is not None and is_file(truth) else None))
    if assets:
        library = Path(assets)
    else:
        library = next((c for c in library_candidates(path, data_root) if (c / "index.json").exists()), None)
    if assets and not (library / "index.json").exists():  # the one given is named, not "give assets="
        raise FileNotFoundError(f"spread-view: assets={assets}: no asset library there (missing index.json)")
    if library is None or not (library / "index.json").exists():
        raise FileNotFoundError(f"spread-view: no asset library for {path} (looked beside it and in the dataset); "
                                "give assets=DIR")
    items = readable(items, library, refused if path.is_dir() else None)
    return items, library


def run_record(path: Path) -> Path | None:
    """The ``sampling.json`` of the sampling run ``path`` belongs to: the run folder's own, or its ``scenes/``
    folder's or one scene file's there (``spread-view <run>/scenes``: as ``spread-export`` finds it); None for
    scenes of no sampling run."""
    folder = path if path.is_dir() else path.parent
    for candidate in (folder / "sampling.json", *((folder.parent / "sampling.json",) if folder.name == "scenes" else ())):
        if candidate.is_file():
            return candidate
    return None


def is_file(path: Path) -> bool:
    """``path.is_file()``, False where the file system cannot even look (a name too long)."""
    try:
        return path.is_file()
    except OSError:
        return False


def readable(items: list[ViewItem], library: Path, refused: list | None) -> list[ViewItem]:
    """The items whose scene file reads as a valid scene of ``library``: in a folder (``refused`` given) one that does
    not is named in ``refused`` and left out, the others shown (before: the first bad one ended the viewer with a
    traceback); a single named file that does not is an error naming it."""
    from spread import readonce
    from spread.scene import read_scene

    assets = readonce.asset_library(library)
    known = set(assets)
    kept = []
    for item in items:
        try:  # as the viewer shows it: the file read and checked, each asset's mesh from the library
            item.name.encode("utf-8")  # a file name that is not text: the browser's connection fails on it
            scene = read_scene(item.path)
            unknown = sorted({str(a) for a in scene.asset_id} - known)
            if unknown:
                raise ValueError(f"{item.path}: asset(s) {', '.join(map(repr, unknown[:3]))} not in the library "
                                 f"{library}")
            for asset in sorted({str(a) for a in scene.asset_id}):
                assets.mesh(asset)  # a mesh that does not read: named here, not a traceback when shown
            if item.ground_truth is not None and not truth_readable(item.ground_truth, assets):
                item.ground_truth = None  # shown as "not known", not a traceback when the scene is picked
        except UnicodeEncodeError:
            exc = ValueError(f"{str(item.path)!r}: its name is not valid text (UTF-8)")
            if refused is None:
                raise ValueError(f"spread-view: {exc}") from None
            refused.append(str(exc))
            continue
        except Exception as exc:  # noqa: BLE001 - any unreadable or invalid scene: named, never shown half
            if refused is None:
                raise ValueError(f"spread-view: {exc}") from None
            refused.append(f"{item.path}: {exc}" if str(item.path) not in str(exc) else str(exc))
            continue
        kept.append(item)
    if not kept:
        raise FileNotFoundError(f"spread-view: no scene here reads as a valid scene ({len(items)} refused: "
                                f"{refused[0] if refused else ''})")
    return kept


def truth_readable(path: Path, assets) -> bool:
    """Whether a ground-truth scene file reads as a scene of ``assets`` whose meshes read."""
    from spread.scene import read_scene

    try:
        for asset in {str(a) for a in read_scene(path, assets).asset_id}:
            assets.mesh(asset)
    except Exception:  # noqa: BLE001 - any reason: the scene is shown without it
        return False
    return True


def ground_truth_source(manifest_path: Path) -> tuple[Path | None, str | None]:
    """(the dataset folder, the split) a run's ``sampling.json`` names (:func:`spread.io.sampled_data`), each None
    when not given; ``ValueError`` naming the file and the key when one is not what a sampling run writes (a run
    folder whose record is damaged is refused, as one whose file is not JSON)."""
    from spread.io import sampled_data

    try:
        return sampled_data(manifest_path)
    except ValueError as exc:
        raise ValueError(f"spread-view: {exc}") from None


def ground_truth_id(path: Path) -> str:
    """The graph a generated scene was conditioned on (``conditioned_on``, when it is one plain file name), else its
    name without ``_k<i>``."""
    from spread.safe_load import load_npz

    from spread.io import safe_name

    try:
        with load_npz(path) as data:
            if "conditioned_on" in data.files and np.asarray(data["conditioned_on"]).ndim == 0:
                named = str(data["conditioned_on"])
                if named and safe_name(named) == named:  # one plain file name: never a path out of the split
                    return named
    except (OSError, ValueError):  # not an npz of arrays: the viewer names the problem when it shows the file
        pass
    stem = path.stem
    head, _, tail = stem.rpartition("_k")
    return head if head and tail.isdigit() else stem


def object_meshes(scene, library, offset=(0.0, 0.0, 0.0), poses=None) -> list[tuple[str, np.ndarray, np.ndarray,
                                                                                       tuple[int, int, int]]]:
    """(name ``<i>_<category>``, world vertices (V, 3) float32 shifted by ``offset``, faces (F, 3), RGB) per object;
    ``poses``: (translation (N, 3), rotation (N, 3, 3)) instead of the scene's own."""
    t, R = poses if poses is not None else (scene.translation, scene.rotation)
    out = []
    for i, (aid, cat) in enumerate(zip(scene.asset_id, scene.category)):
        mesh = library.mesh(str(aid))
        V = np.asarray(mesh.vertices, np.float64) @ np.asarray(R[i], np.float64).T + np.asarray(t[i], np.float64)
        out.append((f"{i}_{cat}", (V + np.asarray(offset)).astype(np.float32), np.asarray(mesh.faces, np.int32),
                    category_colour(str(cat), DEFAULT_PALETTE)))
    return out


def width_x(scene, library) -> float:
    from spread.render.perspective import posed_bounds

    lo, hi = posed_bounds(scene, library)
    if scene.room is not None:
        lo, hi = np.minimum(lo, scene.room[0]), np.maximum(hi, scene.room[1])
    return float(hi[0] - lo[0])


def legend_html(scene) -> str:
    from spread.render.figures import legend_entries

    rows = "".join(f'<div><span style="display:inline-block;width:12px;height:12px;margin-right:6px;'
                   f'background:rgb{tuple(int(c) for c in colour)}"></span>{html_text(label)}</div>'
                   for label, colour in legend_entries([str(c) for c in scene.category]))
    return f'<div style="font-size:0.8em">{rows}</div>'


class SceneViewer:
    """The viser server and its panel (module docstring). ``server`` is the :class:`viser.ViserServer`."""

    def __init__(self, items: list[ViewItem], library_root: Path, host: str = "127.0.0.1", port: int = 8080):
        import viser

        from spread.assets.library import AssetLibrary

        self.items = {item.name: item for item in items}
        self.library = AssetLibrary.load(library_root)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+y")
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        self.pick = gui.add_dropdown("scene", tuple(self.items), initial_value=items[0].name)
        self.truth = gui.add_checkbox("ground truth beside", initial_value=True)
        self.physics = gui.add_checkbox("after Stability (simulate)", initial_value=False)
        self.info = gui.add_markdown("")
        self.legend = gui.add_html("")
        self.timeline = None
        self.matrix = None
        self.shown: list[str] = []
        self.bounds: list = []
        for handle in (self.pick, self.truth, self.physics):
            handle.on_update(lambda _: self.show())
        self.show()

    def clear(self) -> None:
        for name in self.shown:
            self.server.scene.remove_by_name(name)
        self.shown = []

    def add_group(self, group: str, scene, offset, label: str, poses=None) -> None:
        for name, V, F, colour in object_meshes(scene, self.library, offset, poses):
            self.server.scene.add_mesh_simple(f"/{group}/{name}", V, F, color=colour, flat_shading=True)
            self.bounds.append((V.min(axis=0), V.max(axis=0)))
        if scene.room is not None:  # the floor: a grid over the room's footprint (y = 0)
            lo, hi = np.asarray(scene.room[0], np.float64), np.asarray(scene.room[1], np.float64)
            self.server.scene.add_grid(f"/{group}/floor", float(hi[0] - lo[0]), float(hi[2] - lo[2]), plane="xz",
                                       cell_size=0.5, position=(float((lo[0] + hi[0]) / 2 + offset[0]), 0.0,
                                                                float((lo[2] + hi[2]) / 2)))
            self.bounds.append((lo + np.asarray(offset), hi + np.asarray(offset)))
        top = max(float(self.library.mesh(str(a)).extents[1]) for a in scene.asset_id) if scene.num_objects else 0
        centre = np.asarray(scene.translation, np.float64).mean(axis=0) if scene.num_objects else np.zeros(3)
        self.server.scene.add_label(f"/{group}/label", label, position=(float(centre[0] + offset[0]),
                                                                         float(top + 1.0), float(centre[2])))
        self.shown.append(f"/{group}")

    def show(self) -> None:
        from spread.render.figures import relation_matrix_figure
        from spread.render.relation_matrix import relation_agreement
        from spread.scene import read_scene

        item = self.items[self.pick.value]
        scene = read_scene(item.path)
        self.clear()
        self.bounds = []
        self.add_group("scene", scene, (0.0, 0.0, 0.0), f"{item.name}")
        step = width_x(scene, self.library) + GAP
        named = "" if str(scene.scene_id) == item.name else f" (scene {markdown_text(scene.scene_id)})"
        lines = [f"**{markdown_text(item.name)}**{named}: {scene.num_objects} objects"]
        x = step
        if self.truth.value and item.ground_truth is not None:
            truth = read_scene(item.ground_truth)
            self.add_group("ground_truth", truth, (x, 0.0, 0.0), f"ground truth {truth.scene_id}")
            lines.append(f"ground truth beside it: {markdown_text(truth.scene_id)}")
            x += max(step, width_x(truth, self.library) + GAP)
        elif item.ground_truth is None:
            lines.append("ground truth: not known for this file")
        if self.physics.value:
            from spread.render.physics_view import after_physics

            outcome = after_physics(scene, self.library)
            self.add_group("after", outcome.after, (x, 0.0, 0.0), "after Stability")
            lines.append(outcome.caption())
        agreement = relation_agreement(scene, self.library)
        lines.append(f"GRecall of its poses: {agreement.matches}/{agreement.pairs} pairs")
        self.info.content = "\n\n".join(lines)
        self.legend.content = legend_html(scene)
        if self.matrix is not None:
            self.matrix.remove()
        self.matrix = self.server.gui.add_image(relation_matrix_figure(agreement, size=4.0), label="relation matrix",
                                                format="png")
        self.add_timeline(scene)
        self.frame()

    def frame(self) -> None:
        """Point the camera (new clients' and the connected ones') at everything shown, from the front (+z) and
        above."""
        if not self.bounds:
            return
        lo = np.min([b[0] for b in self.bounds], axis=0)
        hi = np.max([b[1] for b in self.bounds], axis=0)
        size = float(np.max(hi - lo))
        centre = (lo + hi) / 2 + np.array([0.15 * size, 0.0, 0.0])  # the scene left of the side panel
        position = centre + np.array([0.0, 0.55 * size, 0.7 * size])
        camera = self.server.initial_camera
        camera.look_at, camera.position, camera.up = tuple(centre), tuple(position), (0.0, 1.0, 0.0)
        for client in self.server.get_clients().values():
            client.camera.look_at, client.camera.position = tuple(centre), tuple(position)

    def add_timeline(self, scene) -> None:
        if self.timeline is not None:
            self.timeline.remove()
            self.timeline = None
        frames = scene_timeline(scene)
        if len(frames) < 2:
            return
        self.timeline = self.server.gui.add_slider("guidance iteration", 0, len(frames) - 1, 1, len(frames) - 1)

        def move(_):
            self.server.scene.remove_by_name("/scene")
            k = int(self.timeline.value)
            self.add_group("scene", scene, (0.0, 0.0, 0.0), f"iteration {k}", poses=frames[k])

        self.timeline.on_update(move)


def scene_timeline(scene) -> list[tuple[np.ndarray, np.ndarray]]:
    """The guidance timeline a sample file carries (``spread-sample guidance.record_every=k``): (translation (N, 3)
    metres, rotation (N, 3, 3)) per recorded iteration, first to last; [] without one."""
    t, R = scene.extras.get("trajectory_translation"), scene.extras.get("trajectory_rotation")
    n = scene.num_objects
    if t is None or R is None or not timeline_shapes(t, R, n):  # another shape or text: no timeline, the scene shown
        return []
    return [(np.asarray(t[k], np.float64), np.asarray(R[k], np.float64)) for k in range(len(t))]


def timeline_shapes(t, R, n: int) -> bool:
    """Whether ``t`` (K, n, 3) and ``R`` (K, n, 3, 3) are one timeline of finite numbers for the scene's ``n`` objects
    (a timeline of text, or over other objects, ended the viewer or failed its slider)."""
    t, R = np.asarray(t), np.asarray(R)
    return (t.dtype.kind in "fiu" and R.dtype.kind in "fiu" and t.ndim == 3 and R.ndim == 4 and len(t) == len(R)
            and t.shape[1:] == (n, 3) and R.shape[1:] == (n, 3, 3) and bool(np.isfinite(t).all())
            and bool(np.isfinite(R).all()))
