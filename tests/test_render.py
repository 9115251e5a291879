"""Top-down renders (orientation, palette, painter's order, determinism), sheets and glb export."""

import numpy as np
import pytest

from spread.assets.assemble import box_asset, library_from_specs
from spread.render import (
    PALETTES, TopDownRenderSettings, category_colour, export_glb, hashed_colour, render_before_after,
    render_grid, render_topdown, save_png,
)

from helpers import scene_of

WHITE = (255, 255, 255)
ROOM = np.array([[-2.0, 0.0, -2.0], [2.0, 3.0, 2.0]])


@pytest.fixture(scope="module")
def library(tmp_path_factory):
    root = tmp_path_factory.mktemp("render_lib")
    return library_from_specs(root, [
        box_asset("table", (1.0, 0.75, 0.6), category="dining_table", role="furniture"),
        box_asset("tray", (0.4, 0.04, 0.3), category="tray"),
        box_asset("stick", (1.2, 0.05, 0.1), category="pencil"),
    ])


def yaw(angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def test_box_at_plus_x_is_on_the_right_in_its_colour(library):
    scene = scene_of(["table"], [[1.2, 0.375, 0.0]], categories=["dining_table"], room=ROOM)
    img = render_topdown(scene, library, TopDownRenderSettings(outline=False))
    assert img.shape == (256, 256, 3) and img.dtype == np.uint8
    colour = np.array(category_colour("dining_table"))
    drawn = (img != 255).any(-1)
    cols = np.flatnonzero(drawn.any(0))
    assert cols.min() > 128, "an object at +x must be drawn on the right half"
    assert (img[drawn] == colour).all()
    assert not drawn[:, :128].any() and (img[0, 0] == WHITE).all() and (img[-1, -1] == WHITE).all()
    # footprint size: 1.0 m × 0.6 m at (4 m + 2·0.25 m margin) / 256 px per pixel
    mpp = 4.5 / 256
    rows = np.flatnonzero(drawn.any(1))
    assert abs(len(cols) * mpp - 1.0) < 2 * mpp and abs(len(rows) * mpp - 0.6) < 2 * mpp


def test_plus_z_points_down_the_image_and_yaw_turns_the_footprint(library):
    scene = scene_of(["stick"], [[0.0, 0.025, 1.0]], [yaw(np.pi / 2)], categories=["pencil"], room=ROOM)
    drawn = (render_topdown(scene, library) != 255).any(-1)
    rows, cols = np.flatnonzero(drawn.any(1)), np.flatnonzero(drawn.any(0))
    assert rows.min() > 128, "+z is down the image"
    assert len(rows) > 4 * len(cols), "a stick along x, turned 90° about y, lies along z"


def test_object_on_top_covers_the_object_below(library):
    # the tray is listed first but rests on the table: it must still be painted last (highest top)
    scene = scene_of(["tray", "table"], [[0.3, 0.77, 0.0], [0.0, 0.375, 0.0]], categories=["tray", "dining_table"],
                     room=ROOM)
    img = render_topdown(scene, library)
    mpp, x0 = 4.5 / 256, -2.25

    def pixel(x, z):
        return img[int((z - x0) / mpp), int((x - x0) / mpp)]

    assert (pixel(0.3, 0.0) == category_colour("tray")).all()
    assert (pixel(-0.3, 0.0) == category_colour("dining_table")).all()
    assert (pixel(-1.5, 1.5) == WHITE).all()
    edge = (img != 255).any(-1) & ~(img == category_colour("tray")).all(-1) & ~(img == category_colour("dining_table")).all(-1)
    assert edge.any(), "outlines are drawn by default"


def test_render_is_deterministic_and_bounds_are_explicit(library):
    scene = scene_of(["table", "tray"], [[0.5, 0.375, -0.5], [0.5, 0.77, -0.5]], [yaw(0.3), yaw(1.1)],
                     categories=["dining_table", "tray"], room=ROOM)
    a, b = render_topdown(scene, library), render_topdown(scene, library)
    assert np.array_equal(a, b)
    settings = TopDownRenderSettings(image_size=64, bounds=(-1, -1, 1, 1), margin=0.0, outline=False)
    small = render_topdown(scene_of(["table"], [[0, 0.375, 0]], categories=["dining_table"]), library, settings)
    assert small.shape == (64, 64, 3)
    assert TopDownRenderSettings.from_dict(settings.to_dict()) == settings
    assert "+z down" in settings.to_dict()["orientation"]


def test_palette_is_fixed_distinct_and_never_white():
    table = PALETTES["spread-v1"]
    assert len(table) == 43 and len(set(table.values())) == 43
    assert all(sum(c) < 3 * 230 for c in table.values()), "no colour near white"
    assert category_colour("mug") == table["mug"]
    unknown = category_colour("zebra_rug")
    assert unknown == hashed_colour("zebra_rug") and unknown != WHITE and sum(unknown) < 3 * 230
    with pytest.raises(ValueError, match="palette"):
        TopDownRenderSettings(palette="nope")


def test_save_png_grid_and_before_after(library, tmp_path):
    from PIL import Image

    before = scene_of(["table"], [[0.0, 0.375, 0.0]], categories=["dining_table"], room=ROOM)
    after = before.with_poses([[1.0, 0.375, 0.0]], before.rotation)
    pair = render_before_after(before, after, library, pad=4)
    assert pair.shape == (256 + 8, 2 * 256 + 12, 3)
    left, right = pair[4:260, 4:260], pair[4:260, 264:520]
    lc = np.flatnonzero((left != 255).any(-1).any(0)).mean()
    rc = np.flatnonzero((right != 255).any(-1).any(0)).mean()
    assert rc - lc == pytest.approx(1.0 / (4.5 / 256), abs=2), "same window: a 1 m move is the same shift"
    grid = render_grid([pair[:10, :10]] * 5, ncols=2, pad=1)
    assert grid.shape == (3 * 10 + 4, 2 * 10 + 3, 3)
    path = save_png(pair, tmp_path / "sub" / "pair.png")
    assert np.array_equal(np.asarray(Image.open(path)), pair)
    assert [p.name for p in path.parent.iterdir()] == ["pair.png"]


def test_export_glb_round_trip(library, tmp_path):
    import trimesh

    scene = scene_of(["table", "tray"], [[0.5, 0.375, -0.5], [0.5, 0.77, -0.5]], [yaw(0.3), yaw(1.1)],
                     categories=["dining_table", "tray"], room=ROOM)
    path = export_glb(scene, library, tmp_path / "scene.glb")
    loaded = trimesh.load(path)
    nodes = {n: loaded.graph[n] for n in loaded.graph.nodes_geometry}
    assert set(nodes) == {"0_table", "1_tray", "floor"}
    for i, aid in enumerate(scene.asset_id):
        T, geom = nodes[f"{i}_{aid}"]
        world = trimesh.transform_points(loaded.geometry[geom].vertices, T)
        expected = library.mesh(aid).vertices @ scene.rotation[i].T.astype(float) + scene.translation[i]
        assert np.allclose(world.min(0), expected.min(0), atol=1e-5)
        assert np.allclose(world.max(0), expected.max(0), atol=1e-5)
        colour = loaded.geometry[geom].visual.material.baseColorFactor[:3]
        assert tuple(int(c) for c in colour) == category_colour(scene.category[i])
    T, geom = nodes["floor"]
    fb = trimesh.transform_points(loaded.geometry[geom].vertices, T)
    assert fb[:, 1].max() == pytest.approx(0.0, abs=1e-6)
    assert np.allclose(fb.min(0)[[0, 2]], ROOM[0, [0, 2]]) and np.allclose(fb.max(0)[[0, 2]], ROOM[1, [0, 2]])
    no_floor = trimesh.load(export_glb(scene, library, tmp_path / "nofloor.glb", floor=False))
    assert len(no_floor.graph.nodes_geometry) == 2
