"""3D views (camera, TinyRenderer), the relation matrix, before | after physics, figures, and no display needed."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from spread.assets.assemble import box_asset, library_from_specs
from spread.render import (
    Camera, PerspectiveSettings, after_physics, agreement_colours, before_after_figure, category_colour,
    default_camera, fit_camera, legend_entries, relation_agreement, relation_matrix_figure, render_perspective,
    scene_card_figure, scene_figure,
)
from spread.render.camera import box_corners
from spread.render.figures import _figure, draw_relation_matrix, figure_array
from spread.render.perspective import FLOOR_LABEL
from spread.render.relation_matrix import MATCH, MISMATCH, SELF
from spread.scene import SPATIAL_ABOVE, SPATIAL_LEFT, SPATIAL_RIGHT

from helpers import scene_of

ROOM = np.array([[-2.0, 0.0, -2.0], [2.0, 3.0, 2.0]])
SMALL = PerspectiveSettings(width=160, height=120, supersample=1)


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    root = tmp_path_factory.mktemp("render3d_lib")
    return library_from_specs(root, [
        box_asset("table", (1.0, 0.75, 0.6), category="dining_table", role="furniture"),
        box_asset("crate", (0.5, 0.5, 0.5), category="box", role="furniture"),
        box_asset("tray", (0.4, 0.04, 0.3), category="tray"),
    ])


def table_tray_crate(library, lift=0.0):
    return scene_of(["table", "tray", "crate"], [[0.0, 0.375, 0.0], [0.0, 0.77 + lift, 0.0], [1.2, 0.25, 0.8]],
                    categories=["dining_table", "tray", "box"], library=library, posed_codes=True, room=ROOM)


def cosine(a, b):
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


# ---- camera ----------------------------------------------------------------------------------------

def test_camera_matrices_equal_pybullets_for_the_same_eye_target_and_lens():
    import pybullet

    cam = Camera(eye=(3.0, 2.5, 4.0), target=(0.2, 0.3, -0.1), fov_y=45.0, aspect=4 / 3, near=0.1, far=30.0)
    view, projection = cam.gl_matrices()
    assert np.allclose(view, pybullet.computeViewMatrix(cam.eye, cam.target, [0, 1, 0]), atol=1e-6)
    assert np.allclose(projection, pybullet.computeProjectionMatrixFOV(45.0, 4 / 3, 0.1, 30.0), atol=1e-6)


def test_fitted_camera_keeps_every_corner_inside_and_fills_the_tighter_side():
    lo, hi = np.array([-2.0, 0.0, -1.5]), np.array([2.5, 1.2, 1.5])
    margin = 0.05
    cam = fit_camera(lo, hi, aspect=4 / 3, elevation=35.0, azimuth=25.0, margin=margin)
    px, depth = cam.project(box_corners(lo, hi), 400, 300)
    assert (depth > cam.near).all() and (depth < cam.far).all()
    assert (px[:, 0] >= 0).all() and (px[:, 0] <= 400).all() and (px[:, 1] >= 0).all() and (px[:, 1] <= 300).all()
    # centred, and the tighter axis leaves exactly `margin` of the half-size free on both sides
    free_x = np.array([px[:, 0].min(), 400 - px[:, 0].max()]) / 200
    free_y = np.array([px[:, 1].min(), 300 - px[:, 1].max()]) / 150
    assert abs(free_x[0] - free_x[1]) < 1e-6 and abs(free_y[0] - free_y[1]) < 1e-6
    assert min(free_x[0], free_y[0]) == pytest.approx(margin, abs=1e-6)


def test_fit_camera_rejects_a_flat_or_upside_down_view():
    with pytest.raises(ValueError, match="elevation"):
        fit_camera(np.zeros(3), np.ones(3), aspect=1.0, elevation=90.0)
    with pytest.raises(ValueError, match="lo <= hi"):
        fit_camera(np.ones(3), np.zeros(3), aspect=1.0)


# ---- 3D view ---------------------------------------------------------------------------------------

def test_3d_view_has_its_size_and_draws_each_object_in_its_category_colour(library):
    scene = table_tray_crate(library)
    image, labels = render_perspective(scene, library, SMALL, return_labels=True)
    assert image.shape == (120, 160, 3) and image.dtype == np.uint8 and labels.shape == (120, 160)
    assert set(np.unique(labels)) == {-1, FLOOR_LABEL, 0, 1, 2}
    assert image.std() > 20, "the image must not be blank"
    assert (image[labels == -1] == 255).all(), "background stays white"
    for i, category in enumerate(scene.category):
        median = np.median(image[labels == i].astype(float), axis=0)
        assert cosine(median, category_colour(category)) > 0.97, (category, median)
    # shaded, not flat: the table's faces turned to the light differ in brightness
    table = image[labels == 0].astype(float).sum(1)
    assert table.max() - table.min() > 40


def test_default_view_puts_plus_x_on_the_right_and_plus_z_nearer_the_bottom(library):
    scene = scene_of(["crate", "crate", "crate"], [[1.4, 0.25, 0.0], [-1.4, 0.25, 0.0], [0.0, 0.25, 1.4]],
                     categories=["box", "box", "box"], library=library, posed_codes=True, room=ROOM)
    _, labels = render_perspective(scene, library, PerspectiveSettings(width=160, height=120, supersample=1,
                                                              azimuth=0.0), return_labels=True)
    centre = [np.argwhere(labels == i).mean(0) for i in range(3)]  # (row, column)
    assert centre[0][1] > 100 > 60 > centre[1][1], "+x right, −x left"
    assert centre[2][0] > max(centre[0][0], centre[1][0]), "+z comes towards the viewer (lower in the image)"


def test_a_given_camera_makes_two_renders_comparable(library):
    scene = table_tray_crate(library)
    moved = table_tray_crate(library, lift=0.4)
    camera = default_camera([scene, moved], library, SMALL)
    a = render_perspective(scene, library, SMALL, camera)
    b = render_perspective(scene, library, SMALL, camera)
    c = render_perspective(moved, library, SMALL, camera)
    assert (a == b).all(), "the same scene and camera give the same pixels"
    assert (np.abs(a.astype(int) - c).max(-1) > 30).mean() > 0.002, "a lifted tray changes the picture"


# ---- relation matrix -------------------------------------------------------------------------------

def test_relation_matrix_is_red_exactly_where_the_graph_is_not_realised(library):
    from spread.metrics import scene_graph_recall

    scene = table_tray_crate(library)
    assert scene.spatial[1, 0] == SPATIAL_ABOVE and scene.spatial[2, 0] == SPATIAL_RIGHT
    scene.spatial[2, 0] = SPATIAL_LEFT  # the graph says the crate is left of the table; the poses say right
    agreement = relation_agreement(scene, library)
    colours = agreement_colours(agreement)
    expected = np.empty((3, 3, 3), np.uint8)
    expected[:] = MATCH
    expected[2, 0] = MISMATCH
    expected[[0, 1, 2], [0, 1, 2]] = SELF
    assert (colours == expected).all()
    assert agreement.matches == scene_graph_recall(scene, library).matches == 5 and agreement.pairs == 6

    # and as drawn: inside the matrix axes, the red pixels are exactly the cell of row 2, column 0
    fig = _figure(4.0, 4.0)
    ax = fig.subplots()
    draw_relation_matrix(ax, agreement)
    image = figure_array(fig)
    box = ax.get_window_extent()  # pixels, origin at the bottom left
    top, left = int(round(image.shape[0] - box.y1)), int(round(box.x0))
    inside = image[top:int(round(image.shape[0] - box.y0)), left:int(round(box.x1))]
    red = (inside == MISMATCH).all(-1)
    rows, cols = np.nonzero(red)
    cell_h, cell_w = inside.shape[0] / 3, inside.shape[1] / 3
    assert red.sum() > 0.6 * cell_h * cell_w
    assert rows.min() >= 2 * cell_h - 2 and cols.max() <= cell_w + 2, "red only in row 2, column 0"
    assert relation_matrix_figure(agreement).shape == (540, 500, 3)


# ---- physics ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def settled_room(tmp_path_factory):
    """A ground-truth room of the generator (settled by its physics), with a small asset library."""
    from spread.assets.build import build_library
    from spread.procgen.room import generate_room
    from spread.procgen.room_types import RoomConfig
    from spread.procgen.settle import SettleConfig

    lib = build_library(tmp_path_factory.mktemp("room_lib"), categories=["dining_table", "chair", "plate", "bowl"],
                        variants=1, progress=False)
    result = generate_room("gt", np.random.default_rng(0), lib, RoomConfig(room_types={"dining_room": 1.0},
                                                                           max_objects=8), SettleConfig())
    assert result.scene is not None and result.scene.num_objects >= 3
    return result.scene, lib


def test_before_and_after_physics_of_a_settled_room_show_no_motion(settled_room):
    scene, lib = settled_room
    outcome = after_physics(scene, lib, seed=3)
    assert outcome.distance.max() < 0.005 and outcome.angle.max() < 0.02 and outcome.moved == 0
    camera = default_camera([outcome.before, outcome.after], lib, SMALL)
    before = render_perspective(outcome.before, lib, SMALL, camera)
    after = render_perspective(outcome.after, lib, SMALL, camera)
    changed = (np.abs(before.astype(int) - after).max(-1) > 40).mean()
    assert changed < 0.003, f"{changed:.4f} of the pixels changed"
    figure = before_after_figure(scene, lib, SMALL, outcome=outcome)
    assert figure.shape[1] > 2 * 160 and figure.std() > 20


def test_before_and_after_physics_shows_a_floating_tray_fall(library):
    outcome = after_physics(table_tray_crate(library, lift=0.3), library)
    assert outcome.moved == 1 and outcome.distance[1] == pytest.approx(0.3, abs=0.02)
    assert outcome.after.translation[1, 1] == pytest.approx(0.77, abs=0.01)
    assert "1/3 objects moved" in outcome.caption()


# ---- figures and headless use ----------------------------------------------------------------------

def test_legend_lists_each_category_once_most_frequent_first():
    entries = legend_entries(["chair", "mug", "chair", "bowl", "chair", "mug"])
    assert [label for label, _ in entries] == ["chair ×3", "mug ×2", "bowl"]
    assert entries[0][1] == category_colour("chair")


def test_scene_figures_are_sized_and_not_blank(library):
    scene = table_tray_crate(library)
    view = scene_figure(scene, library, SMALL)
    card = scene_card_figure(scene, library, SMALL)
    assert view.shape[0] == 155 and view.shape[1] > 160 and view.std() > 20
    assert card.shape[1] > view.shape[1] and card.std() > 20
    # the legend's swatch of each category is drawn in its palette colour
    for category in ("dining_table", "tray", "box"):
        assert (view == category_colour(category)).all(-1).sum() > 20


def test_rendering_needs_no_display(library, tmp_path):
    code = (
        "import sys, numpy as np\n"
        "from spread.assets import AssetLibrary\n"
        "from spread.render import PerspectiveSettings, render_perspective, scene_figure, save_png\n"
        "from spread.scene import Scene\n"
        f"lib = AssetLibrary.load({str(library.root)!r})\n"
        "s = Scene('x', ['crate'], ['box'], [[0, 0.25, 0]], [np.eye(3)], [[6]], [[0]])\n"
        "settings = PerspectiveSettings(width=64, height=48, supersample=1)\n"
        "assert render_perspective(s, lib, settings).std() > 10\n"
        f"save_png(scene_figure(s, lib, settings), {str(tmp_path / 'x.png')!r})\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "MPLBACKEND")}
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert Path(tmp_path / "x.png").stat().st_size > 1000
