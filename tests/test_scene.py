"""Scene files: round trips, atomic writes, and clear errors for every kind of bad file."""

import numpy as np
import pytest

from spread.importers.release_boxes import read_reference_boxes
from spread.scene import (
    SceneFormatError, read_scene, write_scene,
)

from helpers import scene_of


def random_scene(n=3, seed=0):
    """``n`` objects at random poses with random spatial codes, one support pair, a room and a ``source`` extra."""
    rng = np.random.default_rng(seed)
    from scipy.spatial.transform import Rotation

    spatial = rng.integers(0, 6, size=(n, n)).astype(np.int8)
    np.fill_diagonal(spatial, 6)
    physical = np.zeros((n, n), np.int8)
    physical[0, 1] = 1
    ids = [f"a{i}" for i in range(n)]
    return scene_of(ids, rng.normal(size=(n, 3)), Rotation.random(n, random_state=seed).as_matrix(),
                    categories=[f"c{i}" for i in range(n)], spatial=spatial, physical=physical,
                    room=np.array([[-2, 0, -2], [2, 3, 2]]), scene_id=f"room_{seed}",
                    extras={"source": np.asarray("ckpt=x.ckpt sampler=ddim50 seed=1")})


def test_round_trip_is_lossless(tmp_path):
    scene = random_scene()
    path = write_scene(scene, tmp_path / "s.npz")
    back = read_scene(path)
    for key, value in scene.to_arrays().items():
        got = back.to_arrays()[key]
        assert got.dtype == value.dtype, key
        np.testing.assert_array_equal(got, value, err_msg=key)
    assert back.scene_id == scene.scene_id
    assert str(back.extras["source"]) == "ckpt=x.ckpt sampler=ddim50 seed=1"


def test_write_is_atomic_and_keeps_old_file_on_failure(tmp_path):
    good = random_scene(seed=1)
    path = write_scene(good, tmp_path / "s.npz")
    bad = random_scene(seed=2)
    bad.translation[0, 0] = np.nan
    with pytest.raises(SceneFormatError):
        write_scene(bad, path)
    assert read_scene(path).scene_id == "room_1"
    assert [p.name for p in tmp_path.iterdir()] == ["s.npz"]  # no temp file left behind


def _write_raw(path, **arrays):
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)
    return path


@pytest.mark.parametrize(
    "key, mutate, problem",
    [
        ("translation", lambda a: a.__setitem__("translation", a["translation"][:2]), "shape"),
        ("translation", lambda a: a["translation"].__setitem__((1, 2), np.inf), "non-finite"),
        ("rotation", lambda a: a["rotation"].__setitem__(0, a["rotation"][0] * 1.1), "orthonormal"),
        ("rotation", lambda a: a["rotation"].__setitem__(0, -np.eye(3)), "determinant"),
        ("spatial", lambda a: a["spatial"].__setitem__((0, 1), 9), "out of range"),
        ("spatial", lambda a: a["spatial"].__setitem__((1, 1), 0), "diagonal"),
        ("physical", lambda a: a["physical"].__setitem__((0, 2), 5), "out of range"),
        ("category", lambda a: a.__setitem__("category", a["category"][:2]), "N = 3"),
        ("physical", lambda a: a.pop("physical"), "missing"),
        ("asset_id", lambda a: [a.__setitem__(k, a[k][:0] if a[k].ndim == 1 else a[k][:0, :0])
                                 for k in ("asset_id", "category", "translation", "rotation", "spatial", "physical")],
         "no objects"),
    ],
)
def test_bad_files_name_file_key_and_problem(tmp_path, key, mutate, problem):
    arrays = random_scene().to_arrays()
    arrays = {k: np.array(v, copy=True) for k, v in arrays.items()}
    mutate(arrays)
    path = _write_raw(tmp_path / "bad.npz", **arrays)
    with pytest.raises(SceneFormatError) as err:
        read_scene(path)
    msg = str(err.value)
    assert str(path) in msg and f"'{key}'" in msg and problem in msg, msg


def test_unknown_asset_is_rejected(tmp_path):
    path = write_scene(random_scene(), tmp_path / "s.npz")
    with pytest.raises(SceneFormatError, match="unknown asset 'a2'"):
        read_scene(path, assets={"a0", "a1"})
    assert read_scene(path, assets={"a0", "a1", "a2"}).num_objects == 3


def test_unreadable_file_is_reported(tmp_path):
    path = tmp_path / "junk.npz"
    path.write_bytes(b"not a zip")
    with pytest.raises(SceneFormatError, match="junk.npz.*not a readable"):
        read_scene(path)


def test_reference_boxes_reader(tmp_path):
    """The release's layout: index 0 placeholder, relations triples, regions_bbox codes."""
    from scipy.spatial.transform import Rotation

    n1 = 4
    R = Rotation.random(n1, random_state=3).as_matrix()
    T = np.arange(n1 * 3, dtype=float).reshape(n1, 3)
    regions = np.full((n1, n1), 0)
    regions[1, 2], regions[2, 1] = 4, 5  # 1 above 2
    np.fill_diagonal(regions, 6)
    relations = np.array([[2, 1, 1], [0, 1, 3], [3, 2, 1]])  # 2 supports 1; root→3 dropped; 3 contacts 1
    path = _write_raw(
        tmp_path / "boxes.npz", T_bbox=T, R_bbox=R, bbox_center=np.ones((n1, 3)) * 0.5,
        obj_names=np.array(["root", "Book_29_unpacked", "RoboTHOR_dining_table_mella", "Plate_9"]),
        relations=relations, regions_bbox=regions, miche_feature=np.zeros((n1, 256, 64)),
    )
    scene = read_reference_boxes(path, scene_id="ProcTHOR-Test-196-room|4")
    assert scene.num_objects == 3
    np.testing.assert_allclose(scene.translation, T[1:])
    np.testing.assert_allclose(scene.rotation, R[1:], atol=1e-6)
    assert scene.physical[1, 0] == 1 and scene.physical[2, 0] == 2 and scene.physical.sum() == 3
    assert scene.spatial[0, 1] == 4 and scene.spatial[1, 0] == 5
    assert list(scene.category) == ["book", "robothor_dining_table_mella", "plate"]
    assert scene.extras["shape_tokens"].shape == (3, 256, 64)
    np.testing.assert_allclose(scene.extras["reference_bbox_center"], 0.5)
    # it converts into a valid scene file
    back = read_scene(write_scene(scene, tmp_path / "conv.npz"))
    np.testing.assert_array_equal(back.physical, scene.physical)


def test_reference_reader_rejects_bad_relations(tmp_path):
    path = _write_raw(
        tmp_path / "boxes.npz", T_bbox=np.zeros((3, 3)), R_bbox=np.tile(np.eye(3), (3, 1, 1)),
        obj_names=np.array(["root", "a_1", "b_2"]), relations=np.array([[1, 7, 2]]),
        regions_bbox=np.full((3, 3), 6),
    )
    with pytest.raises(SceneFormatError, match="'relations'.*predicate 7"):
        read_reference_boxes(path)


def test_atomic_writes_get_normal_file_permissions(tmp_path):
    import os

    from spread.io import write_json_atomic

    umask = os.umask(0o022)
    try:
        write_json_atomic(tmp_path / "m.json", {"a": 1})
        assert (tmp_path / "m.json").stat().st_mode & 0o777 == 0o644
    finally:
        os.umask(umask)


def test_scene_of_gives_identity_rotations_library_categories_and_codes_of_the_poses(tmp_path):
    """``helpers.scene_of``, the tests' one scene builder, fills what it is not given as its docstring says."""
    from spread.assets.assemble import box_asset, library_from_specs

    library = library_from_specs(tmp_path / "assets", [box_asset("crate", (1.0, 0.5, 1.0), category="box")])
    t = [[0.0, 0.25, 0.0], [2.0, 0.25, 0.0]]  # two crates on the floor, 2 m apart along x
    plain = scene_of(["crate", "crate"], t).validate()
    assert np.array_equal(plain.rotation, np.tile(np.eye(3), (2, 1, 1)))
    assert plain.category.tolist() == ["crate", "crate"]  # no library: the ids stand for the categories
    assert plain.spatial.tolist() == [[6, 0], [0, 6]] and not plain.physical.any() and plain.room is None
    posed = scene_of(["crate", "crate"], t, library=library, posed_codes=True, room=[[-3, 0, -3], [3, 3, 3]],
                     scene_id="posed").validate(assets=library)
    assert posed.category.tolist() == ["box", "box"] and posed.scene_id == "posed"
    assert posed.spatial.tolist() == [[6, 1], [0, 6]]  # crate 0 (x = 0) is left of crate 1 (x = 2), 1 right of 0
    with pytest.raises(ValueError, match="library"):
        scene_of(["crate"], t[:1], posed_codes=True)
