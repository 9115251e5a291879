"""The procedural household asset library: geometry, metadata, determinism, stability, physics.

One library (every category × 5 variants, seed 0) is built once per session; everything is in the
canonical frame (metres, y-up, bbox centre at the origin) unless a test says "world" (floor y = 0).
"""

from __future__ import annotations

import os

import numpy as np
import pytest
import trimesh

from spread.assets import AssetLibrary
from spread.assets.build import build_asset, build_library
from spread.assets.assemble import AssetSpec, box_part, write_asset
from spread.assets.catalog import (
    CATALOG, categories_with_tag, default_categories, furniture_categories, make_spec, object_categories,
)
from spread.assets.primitives import horizontal_prism
from spread.assets.shape import LIE_ON_SIDE, rot_x
from spread.assets.stability import check_rest_pose

VARIANTS = 5
REQUIRED_FURNITURE = ["dining_table", "coffee_table", "side_table", "desk", "kitchen_counter", "shelf", "bookcase",
                      "nightstand", "tv_stand", "dresser", "bed", "sofa", "armchair", "chair", "stool"]
REQUIRED_OBJECTS = ["mug", "cup", "bowl", "plate", "bottle", "vase", "book", "laptop", "remote", "phone", "box", "pan",
                    "pot", "fruit", "lamp", "candle", "pillow", "tray", "basket", "can", "toy", "pencil"]
#: Categories whose inside is hollow: their parts must reproduce the mesh exactly.
CONCAVE = ["mug", "cup", "glass", "wine_glass", "bowl", "plate", "pan", "pot", "vase", "tray", "basket"]


@pytest.fixture(scope="session")
def library(tmp_path_factory) -> AssetLibrary:
    return build_library(tmp_path_factory.mktemp("assets"), variants=VARIANTS, seed=0, progress=False)


# ------------------------------------------------------------------------------------------------
# geometry helpers (independent of the code under test)
# ------------------------------------------------------------------------------------------------

def inside_parts(parts, points: np.ndarray, tol: float = 0.0) -> np.ndarray:
    """Which points lie inside (or within ``tol`` outside the planes of) at least one convex part."""
    inside = np.zeros(len(points), bool)
    for part in parts:
        normals = part.face_normals
        offsets = np.einsum("ij,ij->i", normals, part.triangles[:, 0])
        inside |= (points @ normals.T - offsets).max(axis=1) <= tol
    return inside


def winding_inside(mesh, points: np.ndarray) -> np.ndarray:
    """Exact point-in-mesh for a watertight mesh: generalised winding number (solid angles) > 1/2."""
    total = np.zeros(len(points))
    for tri in np.array_split(mesh.triangles, max(1, len(mesh.triangles) // 256)):
        a, b, c = (tri[None, :, k, :] - points[:, None, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(v, axis=2) for v in (a, b, c))
        det = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la \
            + np.einsum("pfi,pfi->pf", c, a) * lb
        total += 2 * np.arctan2(det, den).sum(axis=1)
    return total / (4 * np.pi) > 0.5


def distance_to_part_surfaces(parts, points: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest triangle of any part."""
    tris = np.concatenate([p.triangles for p in parts])
    best = np.full(len(points), np.inf)
    for chunk in np.array_split(np.arange(len(points)), max(1, len(points) // 100)):
        P = np.repeat(points[chunk], len(tris), axis=0)
        T = np.tile(tris, (len(chunk), 1, 1))
        d = np.linalg.norm(trimesh.triangles.closest_point(T, P) - P, axis=1).reshape(len(chunk), len(tris))
        best[chunk] = d.min(axis=1)
    return best


def world_surface_height(rec, surface) -> float:
    """Height above the floor of a support surface, with the asset upright (identity rest pose)."""
    return surface.height + rec.extents[1] / 2


# ------------------------------------------------------------------------------------------------
# catalog and library contents
# ------------------------------------------------------------------------------------------------

def test_catalog_covers_the_required_categories(library):
    cats = default_categories()
    assert len(cats) >= 40
    assert set(REQUIRED_FURNITURE) <= set(furniture_categories())
    assert set(REQUIRED_OBJECTS) <= set(object_categories())
    assert library.categories == cats
    for c in cats:
        assert len(library.ids_of(c)) >= VARIANTS
        assert library.ids_of(c)[0] == f"{c}_00"
    assert {"plate", "bowl", "book", "box", "tray"} <= set(categories_with_tag("stackable"))
    assert {"bowl", "tray", "basket"} <= set(categories_with_tag("container"))


def test_variants_differ_in_shape(library):
    for c in default_categories():
        extents = np.array([library[a].extents for a in library.ids_of(c)])
        assert len(np.unique(extents.round(4), axis=0)) == VARIANTS, c


def test_meshes_are_watertight_centred_and_within_budget(library):
    for aid in library:
        rec, mesh = library[aid], library.mesh(aid)
        assert mesh.is_watertight, aid
        assert mesh.volume > 0 and abs(mesh.volume - rec.volume) <= 1e-4 * rec.volume, aid
        assert np.abs(mesh.bounds.mean(axis=0)).max() < 1e-5, aid
        assert np.allclose(mesh.extents, rec.extents, atol=1e-6), aid
        assert len(mesh.faces) == rec.num_faces <= 5000, aid


def test_every_part_is_convex_and_part_counts_are_modest(library):
    for aid in library:
        parts = library.convex_parts(aid)
        assert len(parts) == library[aid].num_parts <= 24, aid
        assert all(p.is_convex and p.is_watertight for p in parts), aid


def test_mass_is_volume_times_category_density(library):
    for aid in library:
        rec = library[aid]
        assert rec.density == CATALOG[rec.category].density
        assert rec.mass == pytest.approx(rec.volume * rec.density, rel=1e-9)
        assert rec.role == CATALOG[rec.category].role


# ------------------------------------------------------------------------------------------------
# realistic sizes
# ------------------------------------------------------------------------------------------------

#: Height above the floor of the first (top) support surface.
SURFACE_HEIGHT = {
    "dining_table": (0.70, 0.80), "coffee_table": (0.35, 0.50), "side_table": (0.45, 0.70), "desk": (0.70, 0.78),
    "kitchen_counter": (0.85, 0.96), "nightstand": (0.45, 0.70), "tv_stand": (0.35, 0.65), "dresser": (0.70, 1.10),
    "bed": (0.40, 0.70), "sofa": (0.40, 0.50), "armchair": (0.40, 0.50), "chair": (0.42, 0.50), "stool": (0.42, 0.80),
    "bench": (0.40, 0.50),
}
#: Overall height (bbox y extent) of objects standing in their first rest pose.
OBJECT_HEIGHT = {
    "mug": (0.08, 0.12), "cup": (0.04, 0.09), "glass": (0.07, 0.17), "wine_glass": (0.10, 0.22),
    "bowl": (0.03, 0.10), "plate": (0.01, 0.05), "bottle": (0.15, 0.40), "can": (0.07, 0.18), "book": (0.01, 0.06),
    "phone": (0.005, 0.02), "fruit": (0.05, 0.12), "lamp": (0.25, 0.70), "candle": (0.05, 0.32),
    "pillow": (0.05, 0.22), "vase": (0.10, 0.45), "pan": (0.03, 0.15), "pot": (0.06, 0.20),
}


def test_dimensions_are_realistic(library):
    for aid in library:
        rec = library[aid]
        lo, hi = SURFACE_HEIGHT.get(rec.category, (None, None))
        if lo is not None:
            assert lo <= world_surface_height(rec, rec.support_surfaces[0]) <= hi, aid
        lo, hi = OBJECT_HEIGHT.get(rec.category, (None, None))
        if lo is not None:
            assert lo <= rec.extents[1] <= hi, aid
        if rec.role == "object":
            assert 0.005 <= rec.extents.max() <= 1.0, aid
        else:
            assert 0.3 <= rec.extents.max() <= 2.6, aid
    pencils = [library[a].extents.max() for a in library.ids_of("pencil")]
    assert all(0.1 <= v <= 0.22 for v in pencils)


# ------------------------------------------------------------------------------------------------
# support surfaces
# ------------------------------------------------------------------------------------------------

def test_furniture_and_stackables_have_support_surfaces(library):
    needs = set(SURFACE_HEIGHT) | {"shelf", "bookcase", "book", "box", "plate", "tray", "bowl", "basket"}
    for c in needs:
        for aid in library.ids_of(c):
            assert library[aid].support_surfaces, aid


def test_support_surfaces_lie_on_real_faces(library):
    """Just above a surface rectangle is free space, just below it is material."""
    for aid in library:
        rec, parts = library[aid], library.convex_parts(aid)
        half = rec.extents / 2
        for s in rec.support_surfaces:
            assert s.kind in ("top", "shelf", "seat", "bed", "inside"), aid
            (x0, z0), (x1, z1) = s.xz_min, s.xz_max
            assert x0 < x1 and z0 < z1, aid
            assert max(-x0, x1) <= half[0] + 1e-6 and max(-z0, z1) <= half[2] + 1e-6, aid
            assert -half[1] < s.height <= half[1] + 1e-6, aid
            gx, gz = np.meshgrid(np.linspace(x0, x1, 4), np.linspace(z0, z1, 4))
            grid = np.stack([gx.ravel(), np.full(gx.size, s.height), gz.ravel()], axis=1)
            assert not inside_parts(parts, grid + [0, 1e-3, 0]).any(), (aid, s)
            assert inside_parts(parts, grid - [0, 1e-3, 0]).all(), (aid, s)
            if np.isfinite(s.clearance):
                assert s.clearance > 0.05, aid
            if s.kind == "shelf":  # the board above closes the clearance
                centre = np.array([[(x0 + x1) / 2, s.height + s.clearance, (z0 + z1) / 2]])
                assert not inside_parts(parts, centre - [0, 1e-3, 0]).any(), aid
                assert inside_parts(parts, centre + [0, 1e-3, 0]).all(), aid


def test_shelves_have_three_open_levels_with_real_gaps(library):
    for c in ("shelf", "bookcase"):
        for aid in library.ids_of(c):
            rec, parts, mesh = library[aid], library.convex_parts(aid), library.mesh(aid)
            levels = sorted(rec.support_surfaces, key=lambda s: s.height)
            heights = [s.height for s in levels]
            assert len(levels) >= 3 and len(set(np.round(heights, 4))) == len(heights), aid
            assert all(s.clearance > 0.1 for s in levels[:-1]), aid
            mids = np.array([[(s.xz_min[0] + s.xz_max[0]) / 2, s.height + s.clearance / 2,
                              (s.xz_min[1] + s.xz_max[1]) / 2] for s in levels[:-1]])
            assert not inside_parts(parts, mids).any(), aid
            assert not winding_inside(mesh, mids).any(), aid


def test_fit_queries(library):
    from dataclasses import replace

    from spread.assets.queries import assets_fitting, fits_on, posed_extents

    top = library["dining_table_00"].support_surfaces[0]
    mug = library["mug_00"]
    assert fits_on(mug, top)
    assert not fits_on(mug, replace(top, clearance=0.05))  # under a low board
    assert not fits_on(library["sofa_00"], top, pose=library["sofa_00"].rest_poses[0])
    bottle = library["bottle_00"]
    lying = next(p for p in bottle.rest_poses if p.name == "lying")
    assert np.allclose(posed_extents(bottle, lying), bottle.extents[[1, 0, 2]])
    widest_bowl = max(library.ids_of("bowl"), key=lambda a: library[a].extents[0])
    assert assets_fitting(library, library[widest_bowl].support_surfaces[0], categories=["fruit"])


# ------------------------------------------------------------------------------------------------
# the convex decomposition is the mesh
# ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("category", CONCAVE)
def test_parts_reproduce_concave_meshes(library, category):
    aid = library.ids_of(category)[0]
    mesh, parts = library.mesh(aid), library.convex_parts(aid)
    surface, _ = trimesh.sample.sample_surface(mesh, 600, seed=1)
    assert distance_to_part_surfaces(parts, surface).max() < 2e-3
    rng = np.random.default_rng(0)
    points = rng.uniform(*mesh.bounds, size=(6000, 3))
    in_mesh, in_parts = winding_inside(mesh, points), inside_parts(parts, points)
    assert np.count_nonzero(in_mesh != in_parts) <= 0.01 * np.count_nonzero(in_mesh)
    assert sum(p.volume for p in parts) >= mesh.volume * (1 - 1e-6)
    # and the inside is really hollow: the middle of the opening, just above the floor, is empty
    floor = min(s.height for s in library[aid].support_surfaces) if library[aid].support_surfaces else None
    if floor is not None:
        probe = np.array([[0.0, floor + 0.01, 0.0]])
        assert not inside_parts(parts, probe).any() and not winding_inside(mesh, probe).any()


def test_hollow_vessels_are_open_inside(library):
    for c in ("mug", "cup", "glass", "vase", "pot"):
        for aid in library.ids_of(c):
            mesh = library.mesh(aid)
            probe = np.array([[0.0, mesh.bounds[1][1] - 0.01, 0.0]])  # on the axis, 1 cm under the rim
            assert not winding_inside(mesh, probe).any(), aid


# ------------------------------------------------------------------------------------------------
# rest poses
# ------------------------------------------------------------------------------------------------

def test_every_rest_pose_is_statically_stable(library):
    for aid in library:
        rec, mesh = library[aid], library.mesh(aid)
        assert rec.rest_poses, aid
        for pose in rec.rest_poses:
            R = pose.rotation
            assert np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.linalg.det(R) > 0
            check = check_rest_pose(mesh, R)
            assert check.stable and check.margin >= check.required, (aid, pose.name, check.margin)
            assert pose.bottom_offset == pytest.approx(-(mesh.vertices @ R.T)[:, 1].min(), abs=1e-6)


def test_expected_rest_poses_survive(library):
    for c, names in (("bottle", {"upright", "lying"}), ("can", {"upright", "lying"}), ("book", {"flat", "upright"}),
                     ("phone", {"flat"}), ("laptop", {"flat"}), ("remote", {"flat"}), ("box", {"flat"})):
        for aid in library.ids_of(c):
            assert {p.name for p in library[aid].rest_poses} == names, aid
    book = library[library.ids_of("book")[0]]
    weights = {p.name: p.weight for p in book.rest_poses}
    assert weights["flat"] > weights["upright"]


def test_round_cylinder_on_its_side_is_not_stable():
    cylinder = trimesh.creation.cylinder(radius=0.03, height=0.12, sections=32)  # axis along z
    assert not check_rest_pose(cylinder, np.eye(3)).stable  # lying: it would roll
    assert check_rest_pose(cylinder, rot_x(-90.0)).stable  # standing on its end
    decagon = horizontal_prism(0.03, 0.12, (0.0, 0.0, 0.0), axis="x", sides=10)
    assert check_rest_pose(decagon, np.eye(3)).stable  # a 10-sided prism rests on a face


def test_builder_drops_unstable_poses(tmp_path):
    # an L: a tall thin post on a small foot that sticks out to one side; lying on +x it tips over
    parts = [box_part((0.1, 0.02, 0.1), (0.0, 0.01, 0.0)), box_part((0.02, 0.4, 0.1), (-0.04, 0.2, 0.0))]
    spec = AssetSpec("l_00", "l", 0, "object", parts, 500.0,
                     rest_poses={"upright": np.eye(3), "tipping": LIE_ON_SIDE})
    rec = write_asset(tmp_path, spec)
    assert [p.name for p in rec.rest_poses] == ["upright"]
    spec.rest_poses = {"tipping": LIE_ON_SIDE}
    with pytest.raises(ValueError, match="stable"):
        write_asset(tmp_path, spec)


def test_rest_poses_hold_in_pybullet(library):
    """One variant per category, every rest pose: 120 steps of 1/240 s on the y-up floor of
    :class:`spread.physics.PhysicsWorld` (the same bodies the generator and the metrics use)."""
    from scipy.spatial.transform import Rotation

    from spread.physics import PhysicsWorld
    from spread.scene import Scene

    with PhysicsWorld() as world:
        for k, c in enumerate(default_categories()):
            aid = library.ids_of(c)[k % VARIANTS]
            for pose in library[aid].rest_poses:
                start = np.array([[0.2, pose.bottom_offset, -0.1]])
                scene = Scene("pose", [aid], [c], start, pose.rotation[None], [[6]], [[0]])
                world.load_scene(scene, library)
                t0, R0 = world.poses()
                assert np.allclose(t0, start, atol=1e-6)
                world.step(120)
                t1, R1 = world.poses()
                assert np.linalg.norm(t1 - t0) < 0.01, (aid, pose.name)
                assert Rotation.from_matrix(R1[0] @ R0[0].T).magnitude() < 0.05, (aid, pose.name)


# ------------------------------------------------------------------------------------------------
# determinism, resume, caches
# ------------------------------------------------------------------------------------------------

def test_same_seed_gives_identical_files_in_parallel(library, tmp_path):
    cats = ["mug", "bookcase", "bottle", "sofa", "fruit", "laptop"]
    again = build_library(tmp_path, categories=cats, variants=2, seed=0, processes=2, progress=False, caches=False)
    for aid in again:
        assert again[aid].content_hash == library[aid].content_hash, aid


def test_different_seed_gives_different_dimensions():
    for c in ("dining_table", "mug", "book", "shelf"):
        a, b = make_spec(c, 0, seed=0), make_spec(c, 0, seed=1)
        bounds = [np.ptp(np.concatenate([p.vertices for p in s.parts]), axis=0) for s in (a, b)]
        assert not np.allclose(*bounds), c
        again = make_spec(c, 0, seed=0)
        assert all(np.array_equal(p.vertices, q.vertices) for p, q in zip(a.parts, again.parts))


def test_rebuild_resumes_without_rewriting(tmp_path):
    lib = build_library(tmp_path, categories=["mug", "book"], variants=2, progress=False)
    files = [tmp_path / f for a in lib for f in (lib[a].mesh_file, lib[a].parts_file)]
    stamps = {f: os.stat(f).st_mtime_ns for f in files}
    _, built = build_asset(tmp_path, "mug", 0, 0)
    assert not built
    damaged = tmp_path / lib["book_01"].mesh_file
    damaged.unlink()  # a damaged asset is rebuilt, the others are reused untouched
    again = build_library(tmp_path, categories=["mug", "book"], variants=2, progress=False)
    assert damaged.exists()
    assert all(os.stat(f).st_mtime_ns == stamps[f] for f in files if f != damaged)
    assert {a: again[a].content_hash for a in again} == {a: lib[a].content_hash for a in lib}
    assert AssetLibrary.load(tmp_path).records.keys() == lib.records.keys()


def test_a_damaged_geometry_cache_is_rebuilt_from_the_mesh_never_read(tmp_path):
    """A cache with NaN points trained silently (loss NaN, 306 of 309 weights non-finite, exit 0); points of shape
    (N, 2) failed mid-epoch with a traceback naming no file; one point per asset trained silently."""
    spec = make_spec("box", 0, seed=0)
    rec = write_asset(tmp_path, spec)
    lib = AssetLibrary(tmp_path, {rec.asset_id: rec})
    good = lib.geometry(rec.asset_id)
    path = lib.cache_path(rec.asset_id)
    damaged_points = {"nan": np.full_like(good.surface_points, np.nan), "shape2": good.surface_points[:, :2],
                      "few": good.surface_points[:1], "text": np.full(good.surface_points.shape, "x")}
    for name, points in damaged_points.items():
        normals = good.surface_normals[:1] if name == "few" else good.surface_normals
        np.savez(path, surface_points=points, surface_normals=normals, xz_hull=good.xz_hull)
        again = AssetLibrary(tmp_path, {rec.asset_id: rec}).geometry(rec.asset_id)
        assert np.array_equal(again.surface_points, good.surface_points), name
        assert np.array_equal(again.xz_hull, good.xz_hull), name
        with np.load(path) as d:  # the file was written anew
            assert np.array_equal(d["surface_points"], good.surface_points), name
    np.savez(path, surface_points=good.surface_points, surface_normals=good.surface_normals,
             xz_hull=np.array([[0.0, 0.0], [np.inf, 1.0], [1.0, 0.0]]))
    assert np.array_equal(AssetLibrary(tmp_path, {rec.asset_id: rec}).geometry(rec.asset_id).xz_hull, good.xz_hull)


def test_a_mesh_file_that_does_not_read_is_named_with_its_asset_as_a_bad_input(tmp_path):
    """A truncated mesh stopped spread-train with trimesh's "buffer size must be a multiple of element size",
    naming neither the asset nor the file; as an AssetError alone (a KeyError) it was a traceback."""
    from spread.assets.library import AssetError

    rec = write_asset(tmp_path, make_spec("box", 0, seed=0))
    mesh = tmp_path / rec.mesh_file
    mesh.write_bytes(mesh.read_bytes()[:-7])
    with pytest.raises(AssetError, match=rf"{mesh}: mesh file of asset '{rec.asset_id}' does not read as a mesh") as got:
        AssetLibrary(tmp_path, {rec.asset_id: rec}).mesh(rec.asset_id)
    assert isinstance(got.value, ValueError) and not str(got.value).startswith("'")


def test_geometry_caches_are_built_once_and_keyed_by_content(library, tmp_path):
    aid = library.ids_of("mug")[0]
    geo = library.geometry(aid)
    assert len(geo.surface_points) >= 2000 and geo.surface_points.shape == geo.surface_normals.shape
    assert np.allclose(np.linalg.norm(geo.surface_normals, axis=1), 1, atol=1e-4)
    assert len(geo.xz_hull) >= 3
    path = library.cache_path(aid)
    stamp = os.stat(path).st_mtime_ns
    fresh = AssetLibrary.load(library.root)
    assert fresh.build_caches() == 0
    assert os.stat(path).st_mtime_ns == stamp
    # a changed mesh has a new content hash, hence a new cache file
    spec = make_spec("box", 0, seed=0)
    rec = write_asset(tmp_path, spec)
    small = AssetLibrary(tmp_path, {rec.asset_id: rec})
    small.geometry(rec.asset_id)
    old = small.cache_path(rec.asset_id)
    spec.parts = [p.copy().apply_scale(1.1) for p in spec.parts]
    rec2 = write_asset(tmp_path, spec)
    assert rec2.content_hash != rec.content_hash
    small2 = AssetLibrary(tmp_path, {rec2.asset_id: rec2})
    assert small2.cache_path(rec2.asset_id) != old and not small2.cache_path(rec2.asset_id).exists()
    assert small2.build_caches() == 1 and small2.cache_path(rec2.asset_id).exists()
