"""spread-import: the SPREAD release layout and InstructScene's 3D-FRONT layout, with hard meshes
(tests/realdata.py), known answers on the imported rooms, bad input, resuming, per-room-type evaluation.

Imports here use ``decomposition=hull`` (one convex hull per asset, milliseconds) to stay fast; the
default CoACD decomposition is exercised by the slow test at the end and by benchmarks/bench_decomposition.py.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

import realdata
from helpers import user_error
from spread.importers.base import hash_fraction
from spread.importers.run import ImportConfig, import_dataset
from spread.io import safe_name
from spread.scene import read_scene

FAST = dict(processes=1, progress=False, renders=0, decomposition="hull", fidelity_samples=500)


def scenes_by_kind(out: Path, library=None) -> dict:
    found = {}
    for path in sorted(out.glob("*/*.npz")):
        scene = read_scene(path, assets=library)
        found[str(scene.extras["source_tag"]).split("|")[-1] if "|" in str(scene.extras["source_tag"])
              else realdata.KINDS[int(str(scene.extras["source_tag"])[:4])]] = scene
    return found


@pytest.fixture(scope="module")
def release(tmp_path_factory):
    root = tmp_path_factory.mktemp("release")
    src = realdata.release_layout(root / "src")
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(root / "out"), **FAST))
    return root, manifest


@pytest.fixture(scope="module")
def front(tmp_path_factory):
    root = tmp_path_factory.mktemp("front")
    src, splits = realdata.threed_front_layout(root / "threed_front_bedroom", root / "3D-FUTURE-model")
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(root / "out"), splits=str(splits),
                                           room_type="bedroom", future_models=str(root / "3D-FUTURE-model"),
                                           **{**FAST, "processes": 2}))
    return root, manifest


def library_of(out: Path):
    from spread.assets import AssetLibrary

    return AssetLibrary.load(out / "assets")


# ---- names ---------------------------------------------------------------------------------------

def test_safe_name_is_one_collision_free_path_component():
    assert safe_name("Book_29") == "Book_29"
    names = [safe_name(t) for t in ("ProcTHOR-Test-196-room|4", "ProcTHOR-Test-196-room/4", "ProcTHOR-Test-196-room_4",
                                     "../x", "..", ".", "", "a" * 300, "é")]
    assert len(set(names)) == len(names)
    for name in names:
        assert name and "/" not in name and "\\" not in name and name not in (".", "..") and not name.startswith(".")
        assert len(name) <= 120 and safe_name(name) == name  # safe names are fixed points
    assert safe_name("ProcTHOR-Test-196-room|4").startswith("ProcTHOR-Test-196-room_4_")


# ---- the release layout --------------------------------------------------------------------------

def test_release_rooms_import_with_safe_ids_and_their_tags_inside(release):
    root, manifest = release
    out = root / "out"
    assert manifest["failed_rooms"] == 0 and manifest["failed_assets"] == 0
    # no test list in the file: its val list is the test split, val is carved from train (by tag hash)
    assert manifest["counts"] == {"train": 1, "val": 1, "test": 2}
    assert "test = the file's val list" in manifest["splits"]["rule"]
    val = [str(read_scene(p).extras["source_tag"]) for p in (root / "out" / "val").glob("*.npz")]
    assert val == [min(("ProcTHOR-Test-0-room|rest", "ProcTHOR-Test-1-room|sunk"), key=hash_fraction)]
    tags = {str(read_scene(p).extras["source_tag"]): p for p in out.glob("*/*.npz")}
    assert set(tags) == {f"ProcTHOR-Test-{k}-room|{kind}" for k, kind in enumerate(realdata.KINDS)}
    for tag, path in tags.items():
        assert path.stem == safe_name(tag) == read_scene(path).scene_id and "|" not in path.name
    assert json.loads((out / "stats.json").read_text())["bounds_translations"] == [-2.0, 0.0, -2.0, 2.0, 1.5, 2.0]
    assert set(manifest["categories"]) == {"table", "mug", "cube"}


def test_release_meshes_are_merged_welded_and_recentred(release):
    root, _ = release
    lib = library_of(root / "out")
    table, mug, cube = lib["Table_1"], lib["Mug_3"], lib["Cube_7"]
    # five bodies (a closed board, four open legs) kept as one open mesh, in the bbox-centred frame
    assert table.source["cleaning"]["bodies"] == 5 and not table.source["closed"] and "open" in table.tags
    np.testing.assert_allclose(table.source["canonical_offset"], realdata.TABLE_OFFSET, atol=1e-6)
    np.testing.assert_allclose(table.extents, realdata.TABLE, atol=1e-6)
    np.testing.assert_allclose(lib.mesh("Table_1").bounds.mean(0), 0.0, atol=1e-6)
    # the UV-split cube is welded into one closed box of 8 vertices
    assert cube.source["closed"] and cube.source["cleaning"]["vertices"] == 8
    assert cube.source["cleaning"]["merged_vertices"] > 0
    np.testing.assert_allclose(cube.volume, realdata.CUBE ** 3, rtol=1e-6)
    # the open cup: its inverted winding is turned outward (samples' normals point away from the axis)
    assert not mug.source["closed"]
    pts, nrm = lib.surface_points("Mug_3")
    wall = np.abs(pts[:, 1]) < 0.04
    radial = pts[wall][:, [0, 2]]
    assert (np.einsum("ij,ij->i", radial, nrm[wall][:, [0, 2]]) > 0).mean() > 0.99
    for rec in (table, mug):
        assert rec.source["decomposition"]["method"] == "hull" and rec.source["decomposition"]["fidelity"]["hausdorff"] > 0
        assert rec.mass > 0 and rec.volume > 0


@pytest.mark.parametrize("kind", realdata.KINDS)
def test_known_answers_hold_on_imported_open_meshes(release, kind):
    from spread.metrics import scene_collisions, scene_support_distance

    root, _ = release
    lib = library_of(root / "out")
    scene = scenes_by_kind(root / "out", lib)[kind]
    col = scene_collisions(scene, lib)
    asd = scene_support_distance(scene, lib)
    gaps = {(p.supporter, p.supported): p.min_signed_distance for p in asd.pairs}
    assert set(gaps) == {(0, 1), (0, 2)}
    assert abs(gaps[(0, 2)]) < 1e-4  # the cube rests on the table in every room
    if kind == "sunk":  # the cup 3 cm into the top: both collide, its support distance is -3 cm
        assert col.colliding == [True, True, False]
        assert max(p.depth for p in col.pairs) == pytest.approx(realdata.SINK, abs=1e-4)
        assert gaps[(0, 1)] == pytest.approx(-realdata.SINK, abs=1e-4)
    elif kind == "float":
        assert col.num_colliding == 0
        assert gaps[(0, 1)] == pytest.approx(realdata.LIFT, abs=1e-4)
    else:  # rest, and the whole room turned 37° about y: the same answers
        assert col.num_colliding == 0 and all(p.depth < 1e-4 for p in col.pairs)
        assert abs(gaps[(0, 1)]) < 1e-4 and asd.asd < 1e-4


def test_resting_imported_room_is_stable_and_the_floating_cup_falls(release):
    from spread.metrics import scene_stability

    root, _ = release
    lib = library_of(root / "out")
    scenes = scenes_by_kind(root / "out", lib)
    rest = scene_stability(scenes["turned"], lib, runs=2)
    assert rest.stability == 1.0 and rest.still_fraction == 1.0
    floating = scene_stability(scenes["float"], lib, runs=2)
    assert floating.max_displacement[1] == pytest.approx(realdata.LIFT, abs=5e-3)


def test_release_graph_is_kept_and_compared_with_the_platforms(release):
    root, manifest = release
    scenes = scenes_by_kind(root / "out")
    for scene in scenes.values():
        assert scene.physical[0, 1] == 1 and scene.physical[0, 2] == 1 and scene.physical.sum() == 2
    agree = manifest["relations_agreement"]
    assert agree["spatial_agreement"] == 1.0
    # the platform finds every support pair of the file except the floating cup's
    assert agree["file_support"] == 8 and agree["file_support_found"] == 7


def test_reimport_skips_finished_rooms_and_assets(release):
    root, _ = release
    out = root / "out"
    files = sorted(out.glob("*/*.npz")) + sorted((out / "assets" / "meshes").glob("*"))
    before = {p: p.stat().st_mtime_ns for p in files}
    manifest = import_dataset(ImportConfig("spread_release", str(root / "src"), str(out), **FAST))
    assert manifest["this_run"]["rooms_written"] == 0 and manifest["this_run"]["assets_built"] == 0
    assert manifest["counts"] == {"train": 1, "val": 1, "test": 2}
    assert {p: p.stat().st_mtime_ns for p in files} == before


def test_changed_room_is_converted_again_and_a_broken_one_loses_its_file(tmp_path):
    src = realdata.release_layout(tmp_path / "src")
    out = tmp_path / "out"
    import_dataset(ImportConfig("spread_release", str(src), str(out), **FAST))
    rest, sunk = "ProcTHOR-Test-0-room|rest", "ProcTHOR-Test-1-room|sunk"
    moved = realdata.release_boxes("rest")
    moved["T_bbox"][2, 0] += 0.1  # the cup moves 10 cm along x
    np.savez(src / rest / "boxes.npz", **moved)
    (src / sunk / "boxes.npz").write_bytes(b"truncated")
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(out), **FAST))
    assert manifest["this_run"]["rooms_written"] == 1 and manifest["failed_rooms"] == 1
    (rest_file,) = [p for p in out.glob("*/*.npz") if str(read_scene(p).extras["source_tag"]) == rest]
    assert read_scene(rest_file).translation[1, 0] == pytest.approx(realdata.MUG_X + 0.1)
    assert not list(out.glob(f"*/{safe_name(sunk)}.npz"))  # the broken room's old file is gone
    assert sum(manifest["counts"].values()) == 3


def _snapshot(root: Path, skip: Path) -> dict:
    return {str(p): p.stat().st_mtime_ns for p in root.rglob("*") if skip not in p.parents and p != skip}


def test_bad_rooms_are_named_counted_and_the_others_imported(tmp_path):
    src = realdata.release_layout(tmp_path / "src")
    cases = realdata.add_bad_rooms(src, tmp_path / "x")
    out = tmp_path / "out"
    before = _snapshot(tmp_path, out)
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(out), **FAST))
    assert _snapshot(tmp_path, out) == before  # nothing written outside out_dir
    assert sum(manifest["counts"].values()) == 4  # the good rooms
    errors = {e["tag"]: e for e in manifest["errors"]["rooms"]}
    assert manifest["failed_rooms"] == len(cases) == len(errors) == 6
    split = str(src / "train_test_split.json")
    assert errors["../x"]["file"] == split and errors["../x"]["key"].startswith("train[")
    assert "boxes.npz" in errors["nobox-room"]["error"] and errors["nobox-room"]["file"].endswith("boxes.npz")
    for case, key in (("nomesh-room", "obj_names[2]"), ("shapes-room", "R_bbox"), ("nan-room", "T_bbox"),
                      ("pickle-room", "obj_names")):
        assert errors[case]["file"] == str(src / case / "boxes.npz") and errors[case]["key"] == key, errors[case]
    assert "Ghost_9" in errors["nomesh-room"]["error"]
    assert "object array" in errors["pickle-room"]["error"]
    assert not (out / "train" / f"{safe_name('../x')}.npz").exists()


def test_missing_split_file_is_a_clear_error(tmp_path):
    src = realdata.release_layout(tmp_path / "src")
    (src / "train_test_split.json").unlink()
    with pytest.raises(FileNotFoundError, match="train_test_split.json"):
        import_dataset(ImportConfig("spread_release", str(src), str(tmp_path / "out"), **FAST))
    assert not (tmp_path / "out").exists()


def test_broken_mesh_file_fails_its_rooms_only(tmp_path):
    src = realdata.release_layout(tmp_path / "src")
    (src / "meshes" / "Mug_3_unpacked.glb").write_bytes(b"glTF but not really")
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(tmp_path / "out"), **FAST))
    assert manifest["failed_assets"] == 1 and manifest["failed_rooms"] == 4
    assert manifest["errors"]["assets"][0]["file"] == str(src / "meshes" / "Mug_3_unpacked.glb")
    assert all("Mug_3" in e["error"] for e in manifest["errors"]["rooms"])


# ---- InstructScene's 3D-FRONT layout -------------------------------------------------------------

def test_threed_front_rooms_import_with_scaled_meshes_and_room_type(front):
    root, manifest = front
    out = root / "out"
    assert manifest["failed_rooms"] == 0 and manifest["counts"] == {"train": 1, "val": 1, "test": 2}
    assert manifest["room_types"] == {"bedroom": 4}
    lib = library_of(out)
    table = [lib[a] for a in lib if a.startswith(realdata.JIDS[0])]
    assert len(table) == 1 and table[0].category == "desk"
    np.testing.assert_allclose(table[0].extents, realdata.TABLE, atol=1e-6)  # the half-scale model, scaled to sizes
    np.testing.assert_allclose(table[0].source["scale"], 2.0, atol=1e-6)
    for scene in scenes_by_kind(out, lib).values():
        assert str(scene.extras["room_type"]) == "bedroom" and str(scene.extras["source_scene_type"]) == "MasterBedroom"
        np.testing.assert_allclose(scene.room[[0, 1], [0, 2]], [-2.0, 2.0], atol=1e-6)  # floor plan, centred


@pytest.mark.parametrize("kind", ["rest", "sunk", "turned"])
def test_threed_front_known_answers(front, kind):
    from spread.metrics import scene_collisions, scene_support_distance

    root, _ = front
    lib = library_of(root / "out")
    scene = scenes_by_kind(root / "out", lib)[kind]
    # 3D-FRONT has no physical relations: the platform's, from the posed meshes, are the graph
    assert scene.physical[0, 1] == 1 and scene.physical[0, 2] == 1
    col = scene_collisions(scene, lib)
    asd = {(p.supporter, p.supported): p.min_signed_distance for p in scene_support_distance(scene, lib).pairs}
    if kind == "sunk":
        assert col.colliding == [True, True, False]
        assert asd[(0, 1)] == pytest.approx(-realdata.SINK, abs=1e-4)
    else:
        assert col.num_colliding == 0 and abs(asd[(0, 1)]) < 1e-4 and abs(asd[(0, 2)]) < 1e-4


def test_threed_front_without_models_uses_boxes_and_says_so(tmp_path):
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(tmp_path / "out"), splits=str(splits),
                                           room_type="bedroom", **FAST))
    assert manifest["failed_rooms"] == 0 and manifest["meshes"]["boxes"] == manifest["assets"] == 3
    assert "oriented boxes" in manifest["source"]["meshes"]


def test_threed_front_bad_input_is_named(tmp_path):
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    room = sorted(p for p in src.iterdir() if p.is_dir())[0]
    arrays = dict(np.load(room / "boxes.npz"))
    np.savez(room / "boxes.npz", **{**arrays, "sizes": arrays["sizes"][:2]})
    with pytest.raises(FileNotFoundError, match="splits"):
        import_dataset(ImportConfig("threed_front", str(src), str(tmp_path / "o1"), splits=str(tmp_path / "no.csv"),
                                    room_type="bedroom", **FAST))
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(tmp_path / "o2"), splits=str(splits),
                                           room_type="bedroom", **FAST))
    (err,) = manifest["errors"]["rooms"]
    assert err["file"] == str(room / "boxes.npz") and err["key"] == "sizes" and sum(manifest["counts"].values()) == 3


def test_evaluation_reports_per_room_type(front, tmp_path):
    from spread.evaluation import EvalProtocol
    from spread.evaluation.aggregate import per_room_type_values
    from spread.evaluation.work import evaluate_scene

    root, _ = front
    out = root / "out"
    lib = library_of(out)
    protocol = EvalProtocol(stability_runs=1, stability_steps=10)
    records = [evaluate_scene(p, lib, protocol) for p in sorted(out.glob("*/*.npz"))]
    assert all(r["error"] is None and r["room_type"] == "bedroom" for r in records)
    records[0] = {**records[0], "room_type": "livingroom"}  # as if a second room type were evaluated with it
    by_type = per_room_type_values(records, protocol)
    assert set(by_type) == {"bedroom", "livingroom"}
    assert by_type["bedroom"]["n_evaluated"] == 3 and by_type["livingroom"]["n_evaluated"] == 1
    total = sum(m["n_colliding_objects"] for m in by_type.values())
    assert total == sum(r["state"]["col_mesh"]["colliding_objects"] for r in records) == 2  # the sunk room


@pytest.mark.slow
def test_default_coacd_decomposition_keeps_the_resting_room_stable(tmp_path):
    from spread.metrics import scene_stability

    src = realdata.release_layout(tmp_path / "src")
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(tmp_path / "out"),
                                           **{**FAST, "decomposition": "coacd", "fidelity_samples": 2000}))
    lib = library_of(tmp_path / "out")
    assert manifest["decomposition"]["hausdorff_m"]["max"] < 0.06
    result = scene_stability(scenes_by_kind(tmp_path / "out", lib)["rest"], lib, runs=2)
    assert result.stability == 1.0
    # the cup and cube settle on the table's parts, which follow its top within their Hausdorff distance
    table_error = lib["Table_1"].source["decomposition"]["fidelity"]["hausdorff"]
    assert max(result.max_displacement) < table_error


def test_import_command_config_composes_into_the_import_options():
    from helpers import compose

    from spread.configs import to_object
    from spread.importers.run import ImportConfig

    cfg = to_object(compose("import", "source=threed_front", "src=/data/bedroom", "out_dir=/tmp/x",
                                "splits=/data/s.csv", "room_type=bedroom", "+decomposition_settings.threshold=0.03"))
    assert (cfg.source, cfg.splits, cfg.room_type, cfg.future_models) == ("threed_front", "/data/s.csv", "bedroom", None)
    assert cfg.decomposition == "coacd" and cfg.decomposition_settings == {"threshold": 0.03}
    assert cfg.stats == "source" and cfg.processes == 2 and isinstance(cfg, ImportConfig)


def test_threed_front_graph_has_one_rule_and_its_ground_truth_grecall_is_one(tmp_path):
    """InstructScene's relations.npy is compared with the platform's codes, never mixed into the graph: every
    pair is the platform's rule (named in the manifest), so ground-truth GRecall is exactly 1."""
    from spread.metrics.graph_recall import scene_graph_recall

    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    room = sorted(p for p in src.iterdir() if p.is_dir())[0]  # the resting room
    # InstructScene's cache: the cup (1) "above" (0) the table (0), as the platform finds; the table "closely
    # right of" (8) the cube (2), where the platform finds the cube on the table (table below cube)
    np.save(room / "relations.npy", np.array([[1, 0, 0], [0, 8, 2]], np.int64))
    out = tmp_path / "out"
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(out), splits=str(splits),
                                           room_type="bedroom", **FAST))
    library = library_of(out)
    scenes = {str(read_scene(p).extras["source_tag"]): read_scene(p) for p in out.glob("*/*.npz")}
    spatial = scenes[room.name].spatial
    assert (spatial[1, 0], spatial[0, 1]) == (4, 5)  # above / below: file and platform agree
    assert (spatial[0, 2], spatial[2, 0]) == (5, 4)  # the platform's code, not the file's "right of"
    assert manifest["room_counts"]["file_pairs"] == 4 and manifest["room_counts"]["file_pairs_equal"] == 2
    assert "platform" in manifest["relations_rule"] and "relations.npy" in manifest["relations_rule"]
    results = [scene_graph_recall(sc, library) for sc in scenes.values()]
    assert len(results) == 4 and sum(r.matches for r in results) == sum(r.pairs for r in results) > 0


def test_an_imported_threed_front_dataset_trains_samples_evaluates_per_room_type_and_exports(front, tmp_path):
    """Every stage takes the imported folder as it is: a few training steps, samples of its test graphs,
    their evaluation per room type, and an MJCF export of the samples."""
    from helpers import FAST_SAMPLE, FAST_TRAIN, SMALL_MODEL, compose, sample_in_process, train_in_process

    from spread.commands.evaluate import evaluate
    from spread.commands.export import export

    data = front[0] / "out"
    run = tmp_path / "run"
    train_in_process(run, "experiment=quick", f"data.root={data}", "trainer.max_time=null", "trainer.max_steps=2",
                     "data.batch_size=2", *SMALL_MODEL, *FAST_TRAIN)
    sampled = sample_in_process(f"ckpt={run / 'checkpoints' / 'last.ckpt'}", f"data.root={data}",
                                f"out_dir={tmp_path / 'samples'}")
    assert len(sampled.files) == len(list((data / "test").glob("*.npz"))) == 2
    assert all(str(read_scene(p).extras["room_type"]) == "bedroom" for p in sampled.files)
    result = evaluate(compose("evaluate", f"scenes={tmp_path / 'samples' / 'scenes'}", f"reference={data}",
                              f"out_dir={tmp_path / 'eval'}", "logger=none", "protocol.stability_runs=1",
                              "fid.enabled=false", "ray.num_cpus=1", "progress=false", "renders=0"))
    assert result.metrics["n_evaluated"] == 2 and set(result.metrics["per_room_type"]) == {"bedroom"}
    report = export(compose("export", f"scenes={tmp_path / 'samples' / 'scenes'}", f"assets={data / 'assets'}",
                            "format=mjcf", f"out_dir={tmp_path / 'mjcf'}", "progress=false"))
    assert not report.failed and len(list((tmp_path / "mjcf").glob("*.xml"))) == 2


def test_a_class_seen_only_in_test_widens_the_one_hot_and_is_named_unknown(tmp_path):
    """Upstream's stats come from train + val, its one-hot from all splits: a test-only class ('lamp', column 1
    here) widens every file. The width comes from the files, the stats' classes are placed by name on the columns
    train and val use, the extra column is named unknown_1 and listed in the manifest."""
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    rooms = sorted(p for p in src.iterdir() if p.is_dir())
    split_of = dict(line.split(",") for line in splits.read_text().split())
    test_room = next(r for r in rooms if split_of[r.name.split("-house_")[1]] == "test")
    for room in rooms:
        arrays = dict(np.load(room / "boxes.npz"))
        labels = arrays["class_labels"]  # columns desk, mug, box, start, end → desk, lamp, mug, box, start, end
        wide = np.concatenate([labels[:, :1], np.zeros((len(labels), 1), labels.dtype), labels[:, 1:]], axis=1)
        if room == test_room:
            wide[1] = 0
            wide[1, 1] = 1  # the mug is of the test-only class
        np.savez(room / "boxes.npz", **{**arrays, "class_labels": wide})
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(tmp_path / "out"), splits=str(splits),
                                           room_type="bedroom", **FAST))
    assert manifest["failed_rooms"] == 0, manifest["errors"]
    columns = manifest["source"]["class_columns"]
    assert columns["width"] == 6 and columns["extra"] == ["unknown_1"]
    assert columns["names"] == ["desk", "unknown_1", "mug", "box", "start", "end"]
    scenes = {read_scene(p).extras["source_tag"].item(): read_scene(p) for p in (tmp_path / "out").glob("*/*.npz")}
    assert list(scenes[test_room.name].category) == ["desk", "unknown_1", "box"]
    assert all(list(s.category) == ["desk", "mug", "box"] for tag, s in scenes.items() if tag != test_room.name)


def test_a_one_hot_the_stats_cannot_be_placed_on_is_refused_naming_the_widths(tmp_path):
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    for room in sorted(p for p in src.iterdir() if p.is_dir()):
        arrays = dict(np.load(room / "boxes.npz"))
        labels = arrays["class_labels"]
        np.savez(room / "boxes.npz", **{**arrays, "class_labels": np.concatenate([labels, labels[:, :2] * 0], axis=1)})
    (src / "dataset_stats.txt").write_text(json.dumps({"class_labels": ["desk", "mug", "box", "cup", "start", "end"],
                                                        "bounds_translations": [-2.0, 0.0, -2.0, 2.0, 1.5, 2.0]}))
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(tmp_path / "out"), splits=str(splits),
                                           room_type="bedroom", **FAST))
    assert manifest["failed_rooms"] == 4
    assert "7 columns" in json.dumps(manifest["errors"]) and "cannot be placed by name" in json.dumps(manifest["errors"])


def test_a_multi_hot_class_row_fails_its_room_only_and_the_other_rooms_import(tmp_path):
    """A room whose class_labels set several classes per object was imported as its first class, and its assets
    (asked with other categories) made every other room fail."""
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    broken = sorted(p for p in src.iterdir() if p.is_dir())[0]
    arrays = dict(np.load(broken / "boxes.npz"))
    np.savez(broken / "boxes.npz", **{**arrays, "class_labels": np.ones_like(arrays["class_labels"])})
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(tmp_path / "out"), splits=str(splits),
                                           room_type="bedroom", **FAST))
    assert manifest["failed_rooms"] == 1 and sum(manifest["counts"].values()) == 3
    assert "classes set; expected one-hot rows" in manifest["errors"]["rooms"][0]["error"]
    assert manifest["errors"]["rooms"][0]["tag"] == broken.name


def test_a_non_finite_class_row_fails_its_room_naming_the_object(tmp_path):
    """NaN is not > 0, so the one-hot checks passed it and argmax read the NaN column as the object's class."""
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    broken = sorted(p for p in src.iterdir() if p.is_dir())[-1]
    arrays = dict(np.load(broken / "boxes.npz"))
    labels = arrays["class_labels"].copy()
    labels[1, 0] = np.nan
    np.savez(broken / "boxes.npz", **{**arrays, "class_labels": labels})
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(tmp_path / "out"), splits=str(splits),
                                           room_type="bedroom", **FAST))
    (err,) = manifest["errors"]["rooms"]
    assert err["tag"] == broken.name and err["key"] == "class_labels" and sum(manifest["counts"].values()) == 3
    assert "object 1 has a non-finite value (nan); expected one-hot rows" in err["error"], err


def test_a_room_that_labels_a_shared_model_otherwise_fails_alone_and_the_rooms_that_agree_keep_their_files(tmp_path):
    """The first room in order used to win an asset id asked with other inputs: one mislabelled object in it failed
    every other room using that model and removed their scene files from an earlier import."""
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    out = tmp_path / "out"
    config = ImportConfig("threed_front", str(src), str(out), splits=str(splits), room_type="bedroom",
                          future_models=str(tmp_path / "models"), **FAST)
    assert import_dataset(config)["failed_rooms"] == 0
    before = sorted(p.name for p in out.glob("*/*.npz"))
    first = sorted(p for p in src.iterdir() if p.is_dir())[0]  # the room that sorts first
    arrays = dict(np.load(first / "boxes.npz"))
    labels = arrays["class_labels"].copy()
    labels[1] = labels[2]  # the mug labelled as the cube's class: the same model asked with another category
    np.savez(first / "boxes.npz", **{**arrays, "class_labels": labels})
    manifest = import_dataset(config)
    (err,) = manifest["errors"]["rooms"]
    assert err["tag"] == first.name and manifest["failed_rooms"] == 1, manifest["errors"]
    assert "is asked for with other inputs (category: " in err["error"] and "than by 3 other rooms" in err["error"]
    after = sorted(p.name for p in out.glob("*/*.npz"))
    assert len(after) == 3 and set(after) < set(before)  # the three that agree kept theirs; the odd one's is gone


def test_an_importer_refuses_files_that_links_lead_outside_its_folders_and_follows_links_inside(tmp_path):
    """A boxes.npz, a room folder or a mesh linked from outside src was imported: links count only inside the
    input's folder (as scene folders already held)."""
    import shutil

    src = realdata.release_layout(tmp_path / "src")
    outside = tmp_path / "outside"
    outside.mkdir()
    rooms = sorted(p for p in src.iterdir() if p.is_dir() and p.name != "meshes")
    shutil.move(rooms[0] / "boxes.npz", outside / "boxes.npz")
    (rooms[0] / "boxes.npz").symlink_to(outside / "boxes.npz")
    shutil.move(rooms[1] / "boxes.npz", src / "spare.npz")
    (rooms[1] / "boxes.npz").symlink_to(src / "spare.npz")  # a link inside src is followed
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(tmp_path / "out"), **FAST))
    (err,) = manifest["errors"]["rooms"]
    assert err["file"] == str(rooms[0] / "boxes.npz") and "outside" in err["error"] and manifest["failed_rooms"] == 1
    shutil.move(src / "meshes" / "Mug_3_unpacked.glb", outside / "mug.glb")  # every room has the mug
    (src / "meshes" / "Mug_3_unpacked.glb").symlink_to(outside / "mug.glb")
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(tmp_path / "out2"), **FAST))
    mug = [e for e in manifest["errors"]["rooms"] if e["file"] == str(src / "meshes" / "Mug_3_unpacked.glb")]
    assert manifest["failed_rooms"] == 4 and len(mug) == 3  # the fourth: its boxes.npz, as above
    assert all(f"leads to {outside / 'mug.glb'}, outside " in e["error"] for e in mug), mug

    front, splits = realdata.threed_front_layout(tmp_path / "front", tmp_path / "models")
    linked = sorted(p for p in front.iterdir() if p.is_dir())[0]
    shutil.move(linked, outside / linked.name)
    linked.symlink_to(outside / linked.name, target_is_directory=True)
    manifest = import_dataset(ImportConfig("threed_front", str(front), str(tmp_path / "out3"), splits=str(splits),
                                           room_type="bedroom", **FAST))
    (err,) = manifest["errors"]["rooms"]
    assert err["tag"] == linked.name and "outside" in err["error"], err


def test_spread_import_of_no_room_at_all_exits_non_zero_after_its_summary(tmp_path):
    src = realdata.release_layout(tmp_path / "src")
    (src / "meshes" / "Mug_3_unpacked.glb").write_bytes(b"glTF but not really")  # every room has a mug
    line, proc = user_error("spread-import", "source=spread_release", f"src={src}", f"out_dir={tmp_path / 'out'}",
                            "progress=false", "decomposition=hull", "renders=0", "fidelity_samples=0")
    assert line.startswith("spread-import: no room was imported (4 failed; first: "), line
    assert "failed rooms / assets" in proc.stdout


def test_spread_import_refuses_an_out_dir_inside_a_dataset_or_holding_a_training_run(release, tmp_path):
    """Round 18 (docs/robustness.md): ``spread-import`` was the one command writing a dataset that did not ask
    :func:`spread.io.check_folder_kind` — an import into ``<dataset>/train/more`` put a second asset library and
    manifest among the first one's scene files, one into a training run's folder sat beside its checkpoints."""
    root, _ = release
    src, dataset = root / "src", root / "out"
    inside = dataset / "train" / "more"
    line, _ = user_error("spread-import", "source=spread_release", f"src={src}", f"out_dir={inside}",
                         "progress=false", "renders=0")
    assert line.startswith(f"spread-import: out_dir={inside}: lies inside a dataset, {dataset} "), line
    assert not inside.exists()
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    line, _ = user_error("spread-import", "source=spread_release", f"src={src}", f"out_dir={run}", "progress=false",
                         "renders=0")
    assert line.startswith(f"spread-import: out_dir={run}: holds a training run ({run / 'checkpoints'})"), line
    assert sorted(p.name for p in run.iterdir()) == ["checkpoints"]
