"""Room generator: ground-truth grade on every generated room, determinism, resume, the command.

The ground-truth checks (:mod:`spread.procgen.quality`) measure with tools independent of the
generator's own geometry code: exact signed distances from trimesh (not the convex-parts proxy used
for annotation), FCL candidate pairs, and a fresh physics re-simulation.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from spread.assets import AssetLibrary
from spread.procgen.dataset import AssetSource, DatasetConfig, generate_dataset, scene_id_of, split_of
from spread.procgen.quality import MAX_PENETRATION, MAX_SUPPORT_DISTANCE, check_room
from spread.scene import list_scene_files, read_scene

from helpers import asset_library

ROOMS = 10


@pytest.fixture(scope="module")
def library_dir(tmp_path_factory):

    root = tmp_path_factory.mktemp("lib") / "assets"
    asset_library(root)
    return root


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, library_dir):
    out = tmp_path_factory.mktemp("gen") / "data"
    config = DatasetConfig(rooms=ROOMS, seed=3, processes=2, renders=2, assets=AssetSource(copy_from=str(library_dir)))
    manifest = generate_dataset(out, config, progress=False)
    lib = AssetLibrary.load(out / "assets")
    scenes = [read_scene(p, assets=lib) for s in ("train", "val", "test") for p in list_scene_files(out / s)]
    quality = [check_room(s, lib) for s in scenes]
    return out, manifest, lib, scenes, quality


def test_dataset_folder_layout(dataset):
    out, manifest, lib, scenes, _ = dataset
    for name in ("train", "val", "test", "assets/index.json", "stats.json", "manifest.json", "renders/overview.png"):
        assert (out / name).exists(), name
    assert len(scenes) == ROOMS - len(manifest["failed_rooms"]) and len(scenes) >= ROOMS - 1
    assert all(manifest["counts"][s] >= 1 for s in ("train", "val", "test"))
    assert sum(manifest["counts"].values()) == len(scenes)
    assert manifest["statistics"]["objects"] == sum(s.num_objects for s in scenes)
    assert set(manifest["categories"]) == set(lib.categories)
    for s in scenes:
        assert 2 <= s.num_objects <= 52


def test_no_pair_penetrates_deeper_than_1cm(dataset):
    worst = max(q.max_penetration for q in dataset[4])
    assert worst < MAX_PENETRATION, f"deepest penetration {worst:.4f} m"


def test_every_small_object_has_one_supporter_at_under_2mm(dataset):
    quality = dataset[4]
    assert all(not q.objects_without_one_supporter for q in quality), [q.objects_without_one_supporter for q in quality]
    distances = np.concatenate([q.support_distances for q in quality])
    assert len(distances) > 0
    assert distances.max() < MAX_SUPPORT_DISTANCE, f"max {distances.max():.4f} m, mean {distances.mean():.5f} m"


def test_support_graph_is_a_forest_rooted_at_floor_furniture(dataset):
    assert all(not q.forest_errors for q in dataset[4]), [q.forest_errors for q in dataset[4]]


def test_resimulation_moves_at_least_98_percent_under_1cm(dataset):
    quality = dataset[4]
    moved = sum(q.resim_moved for q in quality)
    total = sum(q.num_objects for q in quality)
    assert 1 - moved / total >= 0.98, f"{moved}/{total} objects moved ≥ 1 cm"


def test_checks_catch_a_broken_room(dataset):
    """The checker itself can fail: lift a supported object 5 cm; sink an object into a table top."""
    _, _, lib, scenes, _ = dataset
    pairs = [(s, int(i), int(j)) for s in scenes for i, j in np.argwhere(s.physical == 1)
             if lib[s.asset_id[i]].role == "furniture" and lib[s.asset_id[j]].extents.min() > 0.03]
    tables = [p for p in pairs if p[0].category[p[1]] in ("dining_table", "coffee_table", "desk", "kitchen_counter")]
    scene, i, j = (tables or pairs)[0]
    lifted = scene.with_poses(scene.translation, scene.rotation)
    lifted.translation[j, 1] += 0.05
    q = check_room(lifted, lib, resimulate=True)
    assert q.max_support_distance == pytest.approx(0.05, abs=0.003)
    assert q.resim_moved >= 1
    sunk = scene.with_poses(scene.translation, scene.rotation)
    sunk.translation[j, 1] -= 0.015
    depth = check_room(sunk, lib, resimulate=False).max_penetration
    assert depth == pytest.approx(0.015, abs=0.003) and depth > MAX_PENETRATION


def test_same_seed_gives_identical_files_regardless_of_processes(dataset, library_dir, tmp_path):
    out = dataset[0]
    config = DatasetConfig(rooms=3, seed=3, processes=1, renders=0, assets=AssetSource(copy_from=str(library_dir)))
    generate_dataset(tmp_path / "again", config, progress=False)
    for index in range(3):
        rel = Path(split_of(index, config)) / f"{scene_id_of(index, 3)}.npz"
        if (out / rel).exists():
            assert (tmp_path / "again" / rel).read_bytes() == (out / rel).read_bytes(), rel


def test_resume_skips_existing_rooms(library_dir, tmp_path):
    config = DatasetConfig(rooms=2, seed=5, processes=1, renders=0, assets=AssetSource(copy_from=str(library_dir)))
    generate_dataset(tmp_path, config, progress=False)
    files = sorted(p for split in ("train", "val", "test") for p in (tmp_path / split).glob("*.npz"))
    assert files
    stamps = {f: f.stat().st_mtime_ns for f in files}
    victim = files[0]
    content = victim.read_bytes()
    victim.unlink()
    manifest = generate_dataset(tmp_path, config, progress=False)
    assert manifest["this_run"]["rooms_generated"] == 1
    assert victim.read_bytes() == content
    for f in files[1:]:
        assert f.stat().st_mtime_ns == stamps[f]
    victim.write_bytes(content[:300])  # cut short by something else than the platform's atomic writes
    manifest = generate_dataset(tmp_path, config, progress=False)
    assert manifest["this_run"]["rooms_generated"] == 1 and victim.read_bytes() == content  # made again, not fatal


def test_a_relaunch_reads_each_kept_room_once(library_dir, tmp_path, monkeypatch):
    """A finished dataset relaunched reads each room file once (checked, then counted in the statistics)."""
    import spread.procgen.dataset as dataset_module
    import spread.scene

    config = DatasetConfig(rooms=3, seed=5, processes=1, renders=0, assets=AssetSource(copy_from=str(library_dir)))
    generate_dataset(tmp_path, config, progress=False)
    reads = []
    real = spread.scene.read_scene

    def counted(path, *args, **kwargs):
        reads.append(Path(path).name)
        return real(path, *args, **kwargs)

    monkeypatch.setattr(spread.scene, "read_scene", counted)
    monkeypatch.setattr(dataset_module, "read_scene", counted)
    manifest = generate_dataset(tmp_path, config, progress=False)
    assert manifest["this_run"]["rooms_generated"] == 0
    assert sorted(reads) == sorted(p.name for s in ("train", "val", "test") for p in (tmp_path / s).glob("*.npz"))


def test_command_line(library_dir, tmp_path):
    exe = Path(sys.executable).parent / "spread-generate"
    env = dict(os.environ, WANDB_MODE="disabled")
    out = tmp_path / "cli"
    res = subprocess.run([str(exe), f"out_dir={out}", "rooms=2", "seed=1", "processes=1", "renders=1",
                          "progress=false", f"assets.copy_from={library_dir}"], capture_output=True, text=True, env=env, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    assert "objects per room" in res.stdout
    assert (out / "manifest.json").exists() and (out / "renders" / "overview.png").exists()
    bad = subprocess.run([str(exe), f"out_dir={out}", "room.no_such_knob=1"], capture_output=True, text=True,
                         env=env, timeout=300)
    assert bad.returncode != 0 and "no_such_knob" in (bad.stderr + bad.stdout)
