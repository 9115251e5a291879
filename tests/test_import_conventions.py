"""spread-import measures which way a release file's spatial codes read (as stored, transposed, x or z
mirrored) against the posed meshes, uses the one the data supports, records all in the manifest, and
refuses files whose codes agree under no reading (spread.importers.conventions)."""

from __future__ import annotations

import json

import numpy as np
import pytest

import realdata
from spread.importers.conventions import READINGS, ConventionError, RelationsOptions, read_as, reading_counts
from spread.importers.run import ImportConfig, import_dataset
from spread.scene import read_scene

FAST = dict(processes=1, progress=False, renders=0, decomposition="hull", fidelity_samples=0)
EXTENTS = {"Cube_7": np.array([realdata.CUBE] * 3), "Mug_3": np.array([2 * realdata.MUG_R, realdata.MUG_H,
                                                                        2 * realdata.MUG_R])}


def exact_codes(T, R, names):
    """The platform's codes of exact boxes (what a file in the platform's convention would hold)."""
    from spread.relations import spatial_codes

    corners = np.array([[sx, sy, sz] for sx in (-.5, .5) for sy in (-.5, .5) for sz in (-.5, .5)])
    boxes = [(corners * EXTENTS[n]) @ r.T + t for t, r, n in zip(T, R, names)]
    return spatial_codes(np.array([b.min(0) for b in boxes]), np.array([b.max(0) for b in boxes]))


def scattered_room(rng):
    """(T, R, names): 6–8 cubes and mugs on a 4 × 4 grid of 0.7 m cells (jittered, cubes turned), some mugs
    on cubes: every direction code occurs."""
    cells = rng.permutation(16)[: rng.integers(5, 7)]
    T, R, names = [], [], []
    for c in cells:
        x, z = (c % 4) * 0.7 + rng.uniform(-0.15, 0.15), (c // 4) * 0.7 + rng.uniform(-0.15, 0.15)
        name = "Cube_7" if rng.random() < 0.6 else "Mug_3"
        T.append([x, EXTENTS[name][1] / 2, z])
        R.append(realdata.rot_y(rng.uniform(-np.pi, np.pi)) if name == "Cube_7" else np.eye(3))
        names.append(name)
        if name == "Cube_7" and rng.random() < 0.5:  # a mug resting on it
            T.append([x, realdata.CUBE + realdata.MUG_H / 2, z])
            R.append(np.eye(3))
            names.append("Mug_3")
    return np.array(T), np.array(R), names


def release_with(root, reading: str | None, rooms: int = 3, seed: int = 0):
    """A release folder whose regions_bbox are written in ``reading`` (None: random codes)."""
    src = realdata.release_layout(root)  # meshes, stats and the known-answer rooms (replaced below)
    rng = np.random.default_rng(seed)
    tags = []
    for k in range(rooms):
        T, R, names = scattered_room(rng)
        n1 = len(names) + 1
        codes = exact_codes(T, R, names)
        if reading is None:
            codes = rng.integers(0, 6, codes.shape)
            np.fill_diagonal(codes, 6)
        regions = np.zeros((n1, n1), np.int64)
        regions[1:, 1:] = codes if reading is None else read_as(codes, reading)
        np.fill_diagonal(regions, 6)
        centres = np.zeros((n1, 3))
        centres[1:] = [realdata.CUBE_OFFSET if n == "Cube_7" else np.zeros(3) for n in names]
        tag = f"ProcTHOR-Train-{k}-room|0"
        (src / tag).mkdir()
        np.savez(src / tag / "boxes.npz", T_bbox=np.vstack([np.zeros(3), T]),
                 R_bbox=np.concatenate([np.eye(3)[None], R]), bbox_center=centres,
                 obj_names=np.array(["root"] + names), relations=np.zeros((0, 3), np.int64), regions_bbox=regions)
        tags.append(tag)
    (src / "train_test_split.json").write_text(json.dumps({"train": tags[:-1], "val": tags[-1:]}))
    return src


def test_every_reading_is_an_involution_and_the_counts_find_the_written_one():
    rng = np.random.default_rng(1)
    T, R, names = scattered_room(rng)
    codes = exact_codes(T, R, names)
    for reading in READINGS:
        assert (read_as(read_as(codes, reading), reading) == codes).all()
        counts = reading_counts(read_as(codes, reading), codes)
        assert counts[reading][0] == counts[reading][1] > 0
        assert all(counts[r][0] < counts[r][1] for r in READINGS if r != reading)


@pytest.mark.parametrize("reading", READINGS)
def test_a_release_written_in_any_reading_imports_in_the_platforms_convention(reading, tmp_path, capsys):
    src = release_with(tmp_path / "src", reading)
    out = tmp_path / "out"
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(out), **FAST))
    conv = manifest["relations_convention"]
    assert conv["reading"] == reading and conv["ties"] == [reading]
    assert conv["agreement"][reading] >= 0.98
    assert all(conv["agreement"][r] < 0.98 for r in READINGS if r != reading)
    assert set(conv["agreement"]) == set(READINGS)
    assert f"reading the files' spatial codes {reading}" in capsys.readouterr().out
    assert manifest["relations_agreement"]["spatial_agreement"] >= 0.98  # the written graph, in our convention
    from spread.assets import AssetLibrary
    from spread.metrics.graph_recall import scene_graph_recall

    library = AssetLibrary.load(out / "assets")
    results = [scene_graph_recall(read_scene(p), library) for p in out.glob("*/ProcTHOR-Train-*.npz")]
    assert len(results) == 3 and sum(r.matches for r in results) / sum(r.pairs for r in results) >= 0.98


def test_random_codes_are_refused_naming_the_option(tmp_path):
    src = release_with(tmp_path / "src", None)
    with pytest.raises(ConventionError, match=r"relations\.convention=") as err:
        import_dataset(ImportConfig("spread_release", str(src), str(tmp_path / "out"), **FAST))
    assert "as_stored" in str(err.value) and "transposed" in str(err.value)
    assert not list((tmp_path / "out").glob("*/ProcTHOR-Train-*.npz"))


def test_a_named_reading_the_data_contradicts_is_refused_and_min_agreement_zero_forces_it(tmp_path):
    src = release_with(tmp_path / "src", "x_mirrored")
    with pytest.raises(ConventionError, match="relations.convention"):
        import_dataset(ImportConfig("spread_release", str(src), str(tmp_path / "a"), **FAST,
                                    relations=RelationsOptions("as_stored")))
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(tmp_path / "b"), **FAST,
                                           relations=RelationsOptions("as_stored", min_agreement=0.0)))
    assert manifest["relations_convention"]["reading"] == "as_stored"
    assert manifest["relations_convention"]["chosen_by"].startswith("relations.convention")


def test_the_command_line_refuses_an_unknown_reading(tmp_path):
    from helpers import run_script

    proc = run_script("spread-import", "source=spread_release", f"src={realdata.release_layout(tmp_path / 's')}",
                      f"out_dir={tmp_path / 'o'}", "relations.convention=mirrored", ok=False)
    assert proc.returncode != 0 and "relations.convention='mirrored'" in proc.stderr
