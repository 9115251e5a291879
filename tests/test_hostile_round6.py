"""Hostile inputs and features that meet, round 6 (docs/robustness.md): what an import, a training launch or an
export already wrote is never lost to a bad option, a failed source or a refused relaunch.

* ``spread-import``: a misspelled option is refused before any work (before, every asset failed and the re-import
  deleted every scene); a source whose every room or asset fails keeps the earlier import; a ``spread-generate``
  folder is not imported into; bad ``dataset_stats.txt`` values and non-UTF-8 files are named; a splits CSV with a
  byte-order mark keeps its first room.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

import realdata
from spread.importers.run import ImportConfig, import_dataset

from helpers import user_error

FAST = dict(processes=1, progress=False, renders=0, decomposition="hull", fidelity_samples=0)


@pytest.fixture
def front(tmp_path) -> dict:
    """A 3D-FRONT source of four rooms (boxes: no model folder) and its import into ``out`` (4 scenes, 3 assets)."""
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    out = tmp_path / "out"
    options = dict(splits=str(splits), room_type="bedroom", **FAST)
    manifest = import_dataset(ImportConfig("threed_front", str(src), str(out), **options))
    assert sum(manifest["counts"].values()) == 4
    return {"src": src, "splits": splits, "out": out, "options": options}


def imported(out: Path) -> dict:
    """The scene files and the asset index of an imported folder, with their bytes."""
    files = [*out.glob("*/*.npz"), out / "assets" / "index.json", out / "manifest.json"]
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(files)}


def test_a_reimport_with_a_misspelled_option_is_refused_before_work_and_the_earlier_import_kept(front):
    before = imported(front["out"])
    line, _ = user_error("spread-import", "source=threed_front", f"src={front['src']}", f"out_dir={front['out']}",
                         f"splits={front['splits']}", "room_type=bedroom", "processes=1", "renders=0",
                         "decomposition=hul")
    assert line.startswith("spread-import: decomposition='hul': unknown method (expected one of coacd, vhacd, hull)")
    assert imported(front["out"]) == before
    for option, message in [({"val_fraction": math.nan}, "val_fraction=nan"), ({"val_fraction": -1.0}, "val_fraction=-1"),
                            ({"density": 0.0}, "density=0.0"),
                            ({"decomposition_settings": {"max_hull": 3}}, r"\['max_hull'\] are not settings of 'hull'")]:
        with pytest.raises(ValueError, match=message):
            import_dataset(ImportConfig("threed_front", str(front["src"]), str(front["out"]),
                                        **{**front["options"], **option}))
    assert imported(front["out"]) == before


def test_a_source_whose_every_room_fails_keeps_the_earlier_scenes_and_their_library(front):
    before = imported(front["out"])
    for room in front["src"].iterdir():
        if (room / "boxes.npz").is_file():
            (room / "boxes.npz").write_bytes(b"not a zip")  # a source folder half copied, or not mounted
    with pytest.raises(ValueError, match=r"every one of the 4 rooms failed \(first: .*boxes.npz.*\); the 4 scene "
                                         r"file\(s\) of earlier imports in .* are kept"):
        import_dataset(ImportConfig("threed_front", str(front["src"]), str(front["out"]), **front["options"]))
    assert imported(front["out"]) == before


def test_an_import_into_a_folder_of_generated_rooms_is_refused_before_it_is_touched(tmp_path, front):
    generated = tmp_path / "generated"
    generated.mkdir()
    (generated / "generation.json").write_text(json.dumps({"generator": "spread-procgen-3"}))
    with pytest.raises(ValueError, match="holds a dataset made by spread-generate .not an import.; an import would "
                                         "replace its assets"):
        import_dataset(ImportConfig("threed_front", str(front["src"]), str(generated), **front["options"]))
    (generated / "generation.json").unlink()
    (generated / "manifest.json").write_text(json.dumps({"generator": "spread-procgen-3", "counts": {"train": 20}}))
    with pytest.raises(ValueError, match="made by spread-procgen-3"):
        import_dataset(ImportConfig("threed_front", str(front["src"]), str(generated), **front["options"]))
    assert sorted(p.name for p in generated.iterdir()) == ["manifest.json"]
    # an import's own folder is imported into again (a resume)
    again = import_dataset(ImportConfig("threed_front", str(front["src"]), str(front["out"]), **front["options"]))
    assert again["this_run"]["rooms_written"] == 0


@pytest.mark.parametrize("stats, named", [
    ({"class_labels": 5}, "key 'class_labels': expected a list of names"),
    ({"bounds_translations": [0, 0, 0, "a", 1, 1]}, "key 'bounds_translations': expected six finite numbers"),
    ({"bounds_translations": [0, 0, 0, float("nan"), 1, 1]}, "key 'bounds_translations'"),
    ({"bounds_translations": [2, 0, 0, 1, 1, 1]}, r"key .bounds_translations.: .* with min ≤ max, got \[2, 0, 0, 1"),
])
def test_bad_dataset_stats_values_are_named_by_file_and_key_before_any_room(tmp_path, stats, named):
    src, splits = realdata.threed_front_layout(tmp_path / "src", tmp_path / "models")
    good = json.loads((src / "dataset_stats.txt").read_text())
    (src / "dataset_stats.txt").write_text(json.dumps({**good, **stats}))
    out = tmp_path / "out"
    with pytest.raises(ValueError, match=rf"{src / 'dataset_stats.txt'}: {named}"):
        import_dataset(ImportConfig("threed_front", str(src), str(out), splits=str(splits), room_type="bedroom", **FAST))
    assert not out.exists()


def test_a_splits_csv_with_a_byte_order_mark_keeps_its_first_room_and_a_non_utf8_file_is_named(tmp_path):
    from spread.importers.threed_front import read_splits

    splits = tmp_path / "splits.csv"
    splits.write_bytes("\ufeffBedroom-100,train\r\nBedroom-101,test\r\n".encode())
    assert read_splits(splits) == {"Bedroom-100": "train", "Bedroom-101": "test"}
    splits.write_bytes(b"Bedroom-100,train\nBedroom-\xff101,test\n")
    with pytest.raises(ValueError, match=rf"{splits}: not UTF-8 text \(byte 26: b'\\xff'\)"):
        read_splits(splits)
    stats = tmp_path / "dataset_stats.txt"
    stats.write_bytes(b'{"class_labels": ["bed\xff"]}')
    from spread.importers.spread_release import read_dataset_stats

    with pytest.raises(ValueError, match=rf"{stats}: not UTF-8 text"):
        read_dataset_stats(stats)


# ---- training -------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    from helpers import make_dataset

    return make_dataset(tmp_path_factory.mktemp("r6data"))


def train_two_steps(out: Path, data: Path, *more: str) -> dict:
    from helpers import FAST_TRAIN, SMALL_MODEL, train_in_process

    return train_in_process(out, "experiment=quick", "model.variant=base", f"data.root={data}", "trainer.max_time=null",
                            "trainer.max_steps=2", *SMALL_MODEL, *FAST_TRAIN, *more)


def test_a_refused_training_launch_leaves_the_recorded_config_and_a_resume_sees_rooms_changed_in_place(
        dataset, tmp_path):
    import shutil

    shutil.copytree(dataset.parent, tmp_path / "copy")
    data = tmp_path / "copy" / dataset.name
    out = tmp_path / "run"
    train_two_steps(out, data)
    recorded = (out / ".hydra" / "config.yaml").read_bytes()
    with pytest.raises(ValueError, match=r"trained with other settings than this run's \(model.lr"):
        train_two_steps(out, data, "model.lr=0.02", "ckpt_path=last", "trainer.max_steps=4")
    with pytest.raises(SystemExit, match="holds a training run already"):
        train_two_steps(out, data, "seed=5")
    assert (out / ".hydra" / "config.yaml").read_bytes() == recorded  # before: lr 0.02, then seed 5 recorded
    moved = tmp_path / "moved"
    shutil.copytree(data.parent, moved)  # the same rooms elsewhere resume
    from spread.training.fit import DATA_DIGEST
    from spread.safe_load import load_checkpoint

    assert isinstance(load_checkpoint(out / "checkpoints" / "last.ckpt").get(DATA_DIGEST), str)
    rooms = sorted((data / "train").glob("*.npz"))
    for room in rooms[: len(rooms) // 2]:
        room.unlink()  # the same folder, fewer rooms
    with pytest.raises(ValueError, match="data.root: .* \\(other rooms than it was trained on\\)"):
        train_two_steps(out, data, "ckpt_path=last", "trainer.max_steps=3")
    summary = train_two_steps(out, moved / dataset.name, "ckpt_path=last", "trainer.max_steps=3")
    assert summary["global_step"] == 3


def test_spread_train_ray_holds_the_run_folders_lock_and_refuses_a_changed_resume_before_ray_starts(dataset, tmp_path):
    from helpers import FAST_TRAIN, SMALL_MODEL
    from spread.io import run_lock

    out = tmp_path / "run"
    train_two_steps(out, dataset)
    args = ["experiment=quick", "model.variant=base", f"data.root={dataset}", "trainer.max_time=null",
            *SMALL_MODEL, *FAST_TRAIN, f"out_dir={out}", "ray_train.num_workers=1", "ray_train.num_cpus=1"]
    line, _ = user_error("spread-train-ray", *args, "model.lr=0.02", "ckpt_path=last", "trainer.max_steps=4")
    assert "trained with other settings than this run's (model.lr" in line
    with run_lock(out, "spread-train"):
        line, _ = user_error("spread-train-ray", *args, "ckpt_path=last", "trainer.max_steps=4")
    assert "in use by" in line and not (out / "ray_train").exists()
