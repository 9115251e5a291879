"""Meshes as shipped: file reading and cleaning, winding-number solids for the metrics, decomposition, mass.

Known answers in metres on small analytic shapes: boxes, an open-topped single-layer cup, two overlapping
closed boxes that were never unioned, a single sheet.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import realdata
from spread.assets.mesh_files import MeshFileError, clean_mesh, load_mesh_file
from spread.metrics.solid import solid_mesh


def two_overlapping_boxes():
    """Boxes [0,1]³ and [0.5,1.5]×[0,1]×[0,1] concatenated (each closed, overlapping in x ∈ [0.5, 1])."""
    a = trimesh.creation.box(bounds=[[0, 0, 0], [1, 1, 1]])
    b = trimesh.creation.box(bounds=[[0.5, 0, 0], [1.5, 1, 1]])
    return trimesh.Trimesh(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.faces, b.faces + 8]),
                           process=False)


def test_closed_box_gives_the_exact_signed_distance_by_winding_number():
    box = trimesh.creation.box(extents=(1.0, 0.5, 0.3))
    pts = np.random.default_rng(0).uniform(-0.8, 0.8, (400, 3))
    exact = -trimesh.proximity.signed_distance(box, pts)  # trimesh is positive inside
    np.testing.assert_allclose(solid_mesh(box).signed_distance(pts), exact, atol=1e-9)
    assert solid_mesh(box).buried == 0


def test_open_cup_is_filled_up_to_its_opening():
    cup = clean_mesh(realdata.open_mug().vertices, realdata.open_mug().faces).mesh  # orientation repaired
    solid = solid_mesh(cup)
    half = realdata.MUG_H / 2
    # deep in the cavity: inside, depth = distance to the bottom (2 cm) or the wall (4 cm)
    assert solid.signed_distance(np.array([[0.0, -half + 0.02, 0.0]]))[0] == pytest.approx(-0.02, abs=1e-6)
    # above the rim: outside, distance to the rim circle
    d = solid.signed_distance(np.array([[0.0, half + 0.03, 0.0]]))[0]
    assert d == pytest.approx(np.hypot(0.03, realdata.MUG_R), abs=2e-3)
    # beside the wall: outside by the gap (the 48-gon's flat sides are within 0.4 mm of the circle)
    assert solid.signed_distance(np.array([[realdata.MUG_R + 0.01, 0.0, 0.0]]))[0] == pytest.approx(0.01, abs=5e-4)
    w = solid.winding_number(np.array([[0.0, y, 0.0] for y in (-0.04, 0.0, 0.04)]))
    assert (w > 0.5).all() and w[0] > w[1] > w[2]  # lower in the cup = more enclosed


def test_overlapping_closed_bodies_measure_against_their_union():
    solid = solid_mesh(two_overlapping_boxes())
    assert solid.buried == 4  # the two faces of each box that lie inside the other
    # (0.9, 0.5, 0.5) is inside both; the union's surface is 0.5 away (y and z faces), the buried
    # face x = 1 would have said 0.1
    assert solid.signed_distance(np.array([[0.9, 0.5, 0.5]]))[0] == pytest.approx(-0.5, abs=1e-9)
    assert solid.winding_number(np.array([[0.9, 0.5, 0.5]]))[0] == pytest.approx(2.0, abs=1e-6)
    assert solid.signed_distance(np.array([[1.7, 0.5, 0.5]]))[0] == pytest.approx(0.2, abs=1e-9)


def test_a_single_sheet_is_outside_on_both_sides():
    sheet = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1]], [[0, 2, 1], [0, 3, 2]], process=False)
    d = solid_mesh(sheet).signed_distance(np.array([[0.5, 0.01, 0.5], [0.5, -0.02, 0.5]]))
    np.testing.assert_allclose(d, [0.01, 0.02], atol=1e-9)


def test_mesh_without_surface_has_no_answer():
    flat = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]], process=False)
    with pytest.raises(ValueError, match="asset 'line'.*degenerate"):
        solid_mesh(flat, name="asset 'line'")


def test_min_signed_distance_of_an_open_mesh_is_the_exact_minimum(tmp_path):
    from spread.assets.library import AssetLibrary
    from spread.assets.imported import write_imported_asset
    from spread.metrics.geometry import asset_geometry, min_signed_distance

    cup = clean_mesh(realdata.open_mug().vertices, realdata.open_mug().faces).mesh
    rec = write_imported_asset(tmp_path, "cup", cup, [trimesh.convex.convex_hull(cup.vertices)], "mug", 500.0, {})
    lib = AssetLibrary(tmp_path, {"cup": rec})
    geom = asset_geometry(lib, "cup")
    assert geom.solid is not None and geom.has_openings
    pts = np.random.default_rng(1).uniform(-0.08, 0.08, (500, 3))
    brute = geom.solid.signed_distance(pts)
    value, index = min_signed_distance(geom, pts)
    assert value == pytest.approx(brute.min(), abs=1e-12) and brute[index] == value
    clipped, _ = min_signed_distance(geom, pts + [0.0, 0.2, 0.0], stop_at=0.0)  # all far above: none needed
    assert clipped == np.inf or clipped > 0


def test_procedural_watertight_assets_keep_the_exact_path(tmp_path):
    from spread.assets.assemble import box_asset, library_from_specs
    from spread.metrics.geometry import asset_geometry

    lib = library_from_specs(tmp_path, [box_asset("box", (0.4, 0.3, 0.2))])
    assert asset_geometry(lib, "box").solid is None


# ---- files -------------------------------------------------------------------------------------------

def test_bad_mesh_files_are_named(tmp_path):
    garbage = tmp_path / "broken.glb"
    garbage.write_bytes(b"not a glb at all")
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    for path, problem in ((garbage, "unreadable"), (empty, "no triangles"), (flat, "zero surface area"),
                          (tmp_path / "missing.ply", "does not exist"), (tmp_path / "model.fbx", "unknown mesh format")):
        with pytest.raises(MeshFileError, match=problem) as info:
            load_mesh_file(path)
        assert str(path) in str(info.value)


def test_multi_body_glb_keeps_node_transforms_and_units(tmp_path):
    path = realdata.write_table_glb(tmp_path / "table.glb")
    loaded = load_mesh_file(path)
    assert loaded.bodies == 5 and not loaded.unioned and not loaded.watertight
    np.testing.assert_allclose(loaded.mesh.bounds.mean(0), realdata.TABLE_OFFSET, atol=1e-6)
    np.testing.assert_allclose(np.ptp(loaded.mesh.vertices, axis=0), realdata.TABLE, atol=1e-6)


def test_closed_bodies_are_unioned_into_one_closed_mesh():
    loaded = clean_mesh(two_overlapping_boxes().vertices, two_overlapping_boxes().faces)
    assert loaded.unioned and loaded.watertight and loaded.bodies == 2
    assert loaded.mesh.volume == pytest.approx(1.5, abs=1e-9)


# ---- decomposition and mass ----------------------------------------------------------------------

def test_flat_hulls_are_dropped_unless_everything_is_flat():
    from spread.assets.decompose import _drop_flat, convex_part

    cube = trimesh.creation.box(extents=(0.1, 0.1, 0.1)).vertices
    sheet = np.array([[0, 0, 0], [1, 0, 0], [1, 0, 1], [0, 0, 1.0]])
    assert len(_drop_flat([cube, sheet])) == 1
    kept = _drop_flat([sheet])
    part = convex_part(kept[0])
    assert part.is_watertight and np.ptp(part.vertices[:, 1]) == pytest.approx(0.002)


def test_hull_decomposition_of_a_box_is_exact():
    from spread.assets.decompose import convex_decomposition, decomposition_fidelity

    box = trimesh.creation.box(extents=(0.3, 0.2, 0.1))
    dec = convex_decomposition(box, method="hull")
    assert len(dec.parts) == 1 and decomposition_fidelity(box, dec.parts)["hausdorff"] < 1e-9
    with pytest.raises(ValueError, match="unknown method 'magic'"):
        convex_decomposition(box, method="magic")
    with pytest.raises(ValueError, match="unknown settings"):
        convex_decomposition(two_overlapping_boxes(), method="coacd", colour="red")


def test_parts_mass_frame_equals_the_mesh_frame_of_their_union():
    from spread.physics.shapes import mass_frame, parts_mass_frame

    low = trimesh.creation.box(bounds=[[0, 0, 0], [1, 0.2, 0.5]])
    high = trimesh.creation.box(bounds=[[0, 0.2, 0], [0.3, 1.0, 0.5]])  # an L, touching, not overlapping
    union = trimesh.boolean.union([low, high], engine="manifold")
    for a, b in zip(parts_mass_frame([low, high]), mass_frame(union)):
        np.testing.assert_allclose(np.abs(a), np.abs(b), atol=1e-9)  # principal axes up to sign


def test_an_imported_asset_is_reused_until_its_inputs_or_files_change(tmp_path):
    from spread.assets.imported import import_box_asset

    rec, built = import_box_asset(tmp_path, "crate", (0.4, 0.3, 0.2), "box")
    assert built
    again, built = import_box_asset(tmp_path, "crate", (0.4, 0.3, 0.2), "box")
    assert not built and again.content_hash == rec.content_hash
    _, built = import_box_asset(tmp_path, "crate", (0.4, 0.3, 0.25), "box")  # other extents: another fingerprint
    assert built
    (tmp_path / rec.parts_file).write_bytes(b"damaged")
    _, built = import_box_asset(tmp_path, "crate", (0.4, 0.3, 0.25), "box")  # intact files are required
    assert built
