"""Figures for people: a scene in 3D with its category legend, before | after physics, the relation matrix,
and a scene card (3D view + relation matrix) — each returned as an (H, W, 3) uint8 image (write it with
:func:`spread.render.save_png`).

Drawn with matplotlib on a standalone Agg canvas (no display, pyplot untouched, so a notebook's inline plots
are not disturbed); the 3D views come from :func:`spread.render.perspective.render_perspective`, the matrix
from :mod:`spread.render.relation_matrix`, the simulated poses from :mod:`spread.render.physics_view`.
A figure's pixel size is ``figsize × dpi``.
"""

from __future__ import annotations

from collections import Counter
from typing import Sequence

import numpy as np

from spread.render.palette import DEFAULT_PALETTE, category_colour
from spread.render.perspective import PerspectiveSettings, default_camera, render_perspective
from spread.render.relation_matrix import (
    CODE_KEY, CODE_LETTERS, MATCH, MISMATCH, SELF, RelationAgreement, agreement_colours, relation_agreement,
)

DPI = 100
#: Above this many objects the matrix cells carry no letters (they would be unreadable).
MAX_LETTERED = 16


def _figure(width: float, height: float, constrained: bool = True):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI, facecolor="white", layout="constrained" if constrained else None)
    if constrained:
        fig.get_layout_engine().set(w_pad=0.02, h_pad=0.02, wspace=0.01, hspace=0.01)
    FigureCanvasAgg(fig)
    return fig


def figure_array(fig) -> np.ndarray:
    """The figure's pixels as (H, W, 3) uint8."""
    fig.canvas.draw()
    return np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()


def _rgb(colour) -> tuple[float, float, float]:
    return tuple(c / 255.0 for c in colour)


def legend_entries(categories: Sequence[str], palette: str = DEFAULT_PALETTE) -> list[tuple[str, tuple[int, int, int]]]:
    """(label, colour) per category present, most frequent first (ties by name); label ``"chair ×3"``."""
    counts = Counter(str(c) for c in categories)
    order = sorted(counts, key=lambda c: (-counts[c], c))
    return [(c if counts[c] == 1 else f"{c} ×{counts[c]}", category_colour(c, palette)) for c in order]


def _legend(ax, categories, palette: str, fontsize: float = 7.5) -> None:
    """The category legend on its own (blank) axes, left-aligned, as many columns as needed."""
    from matplotlib.patches import Patch

    ax.set_axis_off()
    entries = legend_entries(categories, palette)
    handles = [Patch(facecolor=_rgb(col), edgecolor="0.3", linewidth=0.4, label=label) for label, col in entries]
    if handles:
        ax.legend(handles=handles, loc="center left", bbox_to_anchor=(0.0, 0.5), frameon=False, fontsize=fontsize,
                  ncols=legend_columns(len(handles)), handlelength=1.2, handleheight=1.0, borderaxespad=0.0,
                  labelspacing=0.35, columnspacing=0.8)


def legend_columns(n: int, rows: int = 20) -> int:
    return max(1, -(-n // rows))


def _legend_width(categories) -> float:
    """Inches for the category legend."""
    return 1.5 * legend_columns(len(set(map(str, categories))))


def _image(ax, image: np.ndarray, title: str = "") -> None:
    ax.imshow(image, interpolation="antialiased")
    ax.set_axis_off()
    if title:
        ax.set_title(title, fontsize=10)


def scene_figure(scene, library, settings: PerspectiveSettings | None = None, title: str | None = None) -> np.ndarray:
    """The 3D view of ``scene`` with its category legend on the right."""
    settings = settings or PerspectiveSettings()
    w, h, legend_w = settings.width / DPI, settings.height / DPI, _legend_width(scene.category)
    fig = _figure(w + legend_w, h + 0.35)
    ax_view, ax_legend = fig.subplots(1, 2, width_ratios=[w, legend_w])
    _image(ax_view, render_perspective(scene, library, settings))
    _legend(ax_legend, scene.category, settings.palette)
    fig.suptitle(scene.scene_id if title is None else title, fontsize=10, x=0.01, ha="left")
    return figure_array(fig)


def before_after_figure(scene, library, settings: PerspectiveSettings | None = None, outcome=None, seed: int = 0,
                        title: str | None = None) -> np.ndarray:
    """The scene as given | after one Stability run (:func:`~spread.render.physics_view.after_physics`, or
    ``outcome`` when already simulated), side by side, both seen by the camera that frames the scene as given
    (objects that physics throws far away leave the picture; the caption gives the largest displacement);
    legend on the right."""
    from spread.render.physics_view import after_physics

    settings = settings or PerspectiveSettings()
    outcome = outcome or after_physics(scene, library, seed=seed)
    camera = default_camera(outcome.before, library, settings)
    views = [render_perspective(s, library, settings, camera) for s in (outcome.before, outcome.after)]
    w, h, legend_w = settings.width / DPI, settings.height / DPI, _legend_width(scene.category)
    fig = _figure(2 * w + legend_w, h + 0.65)
    axes = fig.subplots(1, 3, width_ratios=[w, w, legend_w])
    _image(axes[0], views[0], "as given")
    _image(axes[1], views[1], "after physics")
    _legend(axes[2], scene.category, settings.palette)
    fig.suptitle(f"{scene.scene_id if title is None else title}: {outcome.caption()} (one Stability run, "
                 f"seed {outcome.seed})", fontsize=9.5, x=0.01, ha="left")
    return figure_array(fig)


def draw_relation_matrix(ax, agreement: RelationAgreement, fontsize: float | None = None,
                         legend: bool = True) -> None:
    """The relation matrix of ``agreement`` on matplotlib axes: coloured cells, object labels, letters (up to
    :data:`MAX_LETTERED` objects), the realised share as the title and the colour key above the matrix."""
    from matplotlib.patches import Patch

    n = len(agreement.labels)
    ax.imshow(agreement_colours(agreement), interpolation="nearest", aspect="equal")
    fontsize = fontsize or float(np.clip(150 / max(n, 1), 4.5, 8.0))
    ax.set_xticks(range(n), agreement.labels, rotation=90, fontsize=fontsize)
    ax.set_yticks(range(n), agreement.labels, fontsize=fontsize)
    ax.tick_params(length=0, pad=2)
    ax.set_xticks(np.arange(-0.5, n, 1), minor=True)
    ax.set_yticks(np.arange(-0.5, n, 1), minor=True)
    ax.grid(which="minor", color="white", linewidth=0.6 if n <= 24 else 0.3)
    ax.tick_params(which="minor", length=0)
    for spine in ax.spines.values():
        spine.set_visible(False)
    lettered = n <= MAX_LETTERED
    if lettered:
        for i, j in zip(*np.nonzero(~np.eye(n, dtype=bool))):
            code = int(agreement.found[i, j])
            if 0 <= code < len(CODE_LETTERS):
                ax.text(j, i, CODE_LETTERS[code], ha="center", va="center", color="white",
                        fontsize=fontsize * 0.95, fontweight="bold")
    ax.set_xlabel("object j" + (f"\nletters: relation found in the poses: {CODE_KEY}" if lettered else ""),
                  fontsize=6.5)
    ax.set_ylabel("subject i   (i is … of j)", fontsize=7)
    caption = f"relations realised: {agreement.matches}/{agreement.pairs} = {agreement.recall:.3f}"
    ax.set_title(caption, fontsize=8.5, pad=16 if legend else 4)
    if legend:
        handles = [Patch(facecolor=_rgb(MATCH), label="as in the graph"),
                   Patch(facecolor=_rgb(MISMATCH), label="differs"), Patch(facecolor=_rgb(SELF), label="self")]
        ax.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 1.0), frameon=False, fontsize=7,
                  ncols=3, handlelength=1.0, columnspacing=1.0, borderaxespad=0.1)


def relation_matrix_figure(scene_or_agreement, library=None, size: float = 5.0, title: str | None = None) -> np.ndarray:
    """The relation matrix of a scene (recomputed with ``library``) or of a :class:`RelationAgreement`."""
    agreement = scene_or_agreement if isinstance(scene_or_agreement, RelationAgreement) \
        else relation_agreement(scene_or_agreement, library)
    fig = _figure(size, size + 0.4)
    draw_relation_matrix(fig.subplots(), agreement)
    fig.suptitle(agreement.scene_id if title is None else title, fontsize=10)
    return figure_array(fig)


def scene_card_figure(scene, library, settings: PerspectiveSettings | None = None, title: str | None = None,
                      matrix_size: float | None = None) -> np.ndarray:
    """One scene as a reader of the paper sees it: 3D view | category legend | relation matrix."""
    settings = settings or PerspectiveSettings()
    agreement = relation_agreement(scene, library)
    view = render_perspective(scene, library, settings)
    w, h, legend_w = settings.width / DPI, settings.height / DPI, _legend_width(scene.category)
    m = matrix_size or max(h + 0.6, 4.0)
    fig = _figure(w + legend_w + m, max(h, m) + 0.35)
    axes = fig.subplots(1, 3, width_ratios=[w, legend_w, m])
    _image(axes[0], view)
    _legend(axes[1], scene.category, settings.palette)
    draw_relation_matrix(axes[2], agreement)
    fig.suptitle(scene.scene_id if title is None else title, fontsize=10, x=0.01, ha="left")
    return figure_array(fig)
