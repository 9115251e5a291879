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
import shutil
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
    for room in [p for p in front["src"].iterdir() if p.is_dir()]:
        shutil.rmtree(room)  # the source lists no room at all
    with pytest.raises(ValueError, match=r"the source lists no room \(src=.*\); the 4 scene file\(s\) of earlier"):
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
    ({"bounds_translations": [2, 0, 0, 1, 1, 1]}, r"key .bounds_translations.: .* with min < max on each axis, got \[2"),
    # min = max: the dataset's stats.json refused it only after every room was imported (stats need max > min)
    ({"bounds_translations": [0, 0, 0, 0, 0, 0]}, r"key .bounds_translations.: .* with min < max on each axis, got \[0"),
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


def test_the_data_digest_a_checkpoint_records_is_what_the_rooms_are_wherever_they_lie(dataset, tmp_path):
    from types import SimpleNamespace

    from spread.training.fit import data_digest

    for name in ("a", "b"):
        shutil.copytree(dataset.parent, tmp_path / name)
        shutil.rmtree(tmp_path / name / dataset.name / "val")  # no val split: trained with limit_val_batches=0
    a, b = (SimpleNamespace(hparams={"root": str(tmp_path / n / dataset.name)}) for n in ("a", "b"))
    assert data_digest(a) == data_digest(b)
    next((tmp_path / "b" / dataset.name / "train").glob("*.npz")).unlink()
    assert data_digest(a) != data_digest(b)


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


# ---- evaluation and reports ---------------------------------------------------------------------------------------

def evaluate_fast(scenes: Path, reference: Path, out: Path, *more: str):
    from spread.commands.evaluate import evaluate

    from helpers import compose

    return evaluate(compose("evaluate", f"scenes={scenes}", f"reference={reference}", f"out_dir={out}", "logger=none",
                            "metrics=[grecall]", "fid.enabled=false", "ray.num_cpus=1", "progress=false", "renders=0",
                            *more))


@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_an_evaluation_is_reported_by_what_it_measured_with_its_reference_and_scenes_included(dataset, tmp_path):
    from spread.evaluation.protocol import EvalProtocol, FIDConfig
    from spread.evaluation.run import check_protocol
    from spread.reporting.intervals import folder_records, row_intervals
    from spread.reporting.runs import RunError, folder_identity
    from spread.runtime.fingerprint import differing, settings

    out = tmp_path / "e"
    first = evaluate_fast(dataset / "test", dataset, out, "bootstrap_resamples=0").metrics
    assert first["evaluated_with"]["reference_split"] == "test" and first["bootstrap_resamples"] == 0
    assert first["evaluated_scenes"] == sorted(p.stem for p in (dataset / "test").glob("*.npz"))
    assert row_intervals(first, out) == {}  # none asked for: none drawn from the per-scene lines
    # another reference split: the same per-scene lines, another FID/KID real set, named as a differing setting
    shutil.copytree(out, tmp_path / "v")
    (tmp_path / "v" / ".spread.lock").unlink(missing_ok=True)
    second = evaluate_fast(dataset / "test", dataset, tmp_path / "v", "reference_split=val").metrics
    assert second["run"]["evaluated_this_run"] == 0
    rows = [settings(folder_identity(f, m)) for f, m in ((out, first), (tmp_path / "v", second))]
    assert {"reference_split", "reference"} <= set(differing(rows))
    # a line of a scene the evaluation did not count (another folder evaluated into it) is not its number
    with (out / "per_scene.jsonl").open("a") as fh:
        fh.write(json.dumps({"scene_id": "zz_other", "grecall": 0.0}) + "\n")
    assert [r["scene_id"] for r in folder_records(out)] == first["evaluated_scenes"]
    # a re-run from scratch (resume=false) with another protocol removes the old result before its record says so
    check_protocol(out, EvalProtocol(metrics=["grecall"], stability_runs=5), FIDConfig(enabled=False), False,
                   str(dataset / "assets"))
    assert not (out / "metrics.json").exists() and not (out / "per_scene.jsonl").exists()
    (tmp_path / "v" / ".hydra" / "config.yaml").write_text("protocol: [1, 2\n")
    with pytest.raises(RunError, match=r"v/.hydra/config.yaml: not a readable config"):
        folder_identity(tmp_path / "v", second)


@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_a_fid_backbone_that_cannot_load_is_refused_before_a_finished_evaluation_is_touched(dataset, tmp_path):
    from spread.evaluation.protocol import FIDConfig
    from spread.evaluation.run import check_fid

    out = tmp_path / "e"
    evaluate_fast(dataset / "test", dataset, out)
    kept = {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.is_file() and p.name != ".spread.lock"}
    with pytest.raises(ValueError, match=r"fid.extractor=nosuch_mod:make: cannot be loaded \(ModuleNotFoundError"):
        check_fid(FIDConfig(extractor="nosuch_mod:make"))
    with pytest.raises(ValueError, match="fid.extractor=nosuch_mod:make: cannot be loaded"):
        evaluate_fast(dataset / "test", dataset, out, "fid.enabled=true", "+fid.extractor=nosuch_mod:make")
    assert {p.name: p.read_bytes() for p in sorted(out.iterdir()) if p.is_file() and p.name != ".spread.lock"} == kept


def test_a_refused_second_run_of_a_folder_writes_no_tracker_record_and_an_older_mlflow_run_keeps_its_numbers(
        dataset, tmp_path):
    import subprocess
    import sys

    from spread.io import RunFolderBusy
    from spread.reporting.report import shown_key
    from spread.results.store import made_the_folder

    out = tmp_path / "e"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from spread.io import run_lock\n"
                               f"with run_lock({str(out)!r}, 'spread-evaluate'):\n print('held', flush=True); "
                               "time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RunFolderBusy, match="in use by a running spread-evaluate"):
            evaluate_fast(dataset / "test", dataset, out, "logger=mlflow",
                          f"logger.tracking_uri={tmp_path / 'mlflow.db'}")
        assert sorted(p.name for p in out.iterdir()) == [".spread.lock"]  # no mlflow_run.json, no .hydra
    finally:
        holder.kill()
        holder.wait()
    (out / "mlflow_run.json").write_text(json.dumps({"run_id": "later"}))
    assert made_the_folder("later", out)
    assert not made_the_folder("earlier", out)
    assert shown_key("asd") == ("asd_mm", "mm") and shown_key("grecall") == ("grecall", None)


def test_a_training_workers_bad_setting_is_found_through_rays_wrappers():
    from ray.exceptions import RayTaskError
    from ray.train.base_trainer import TrainingFailedError

    from spread.training.ray_train import worker_user_error

    cause = ValueError("trainer.accelerator=gpu (trainer=gpu): this process sees no CUDA device")
    wrapped = TrainingFailedError("Training failed")
    wrapped.__cause__ = RayTaskError("train_fn", "Traceback ...", cause).as_instanceof_cause()
    assert worker_user_error(wrapped) is cause  # spread-train-ray then says it in one line, not 53
    crash = TrainingFailedError("Training failed")
    crash.__cause__ = RayTaskError("train_fn", "Traceback ...", RuntimeError("CUDA error")).as_instanceof_cause()
    assert worker_user_error(crash) is None  # a crash stays a traceback


def test_a_training_workers_bad_setting_is_found_through_ray_train_v2s_wrappers():
    from ray.train.v2._internal.exceptions import UserExceptionWithTraceback
    from ray.train.v2.api.exceptions import ControllerError, WorkerGroupError

    from spread.training.ray_train import worker_user_error

    first = ValueError("data.root=/x: no scene files in /x/train to train on")
    failures = {1: UserExceptionWithTraceback(RuntimeError("rank 1 crashed"), "Traceback ..."),
                0: UserExceptionWithTraceback(first, "Traceback ...")}
    assert worker_user_error(WorkerGroupError("rank 0, 1", failures)) is first
    assert worker_user_error(ControllerError(first)) is first
    crash = WorkerGroupError("rank 0", {0: UserExceptionWithTraceback(RuntimeError("CUDA error"), "Traceback ...")})
    assert worker_user_error(crash) is None


@pytest.mark.parametrize("key, value, named", [
    ("mass", float("nan"), "mass=nan: expected a finite number of kg > 0"),
    ("mass", float("inf"), "mass=inf"),
    ("extents", [float("nan")] * 3, "extents=\\[nan, nan, nan\\]: expected three finite sizes > 0"),
    ("extents", [0.5, 0.5], "extents=\\[0.5, 0.5\\]"),
    ("extents", [], "extents=\\[\\]"),
    ("density", -1.0, "density=-1.0: expected a finite number ≥ 0"),
])
def test_an_asset_index_with_a_measure_no_physics_or_model_can_use_is_refused_naming_asset_and_key(
        dataset, tmp_path, key, value, named):
    from spread.assets import AssetLibrary

    library = tmp_path / "assets"
    shutil.copytree(dataset / "assets", library)
    index = json.loads((library / "index.json").read_text())
    records = index["assets"]
    first = sorted(records)[0]
    records[first][key] = value
    (library / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match=rf"index.json: asset '{first}' has a bad record \(ValueError: {named}"):
        AssetLibrary.load(library)


def test_a_baseline_is_not_sampled_on_a_dataset_whose_category_list_differs_from_its_training(dataset, tmp_path):
    from helpers import FAST_TRAIN, sample_in_process, train_in_process

    out = tmp_path / "run"
    train_in_process(out, "experiment=atiss_quick", f"data.root={dataset}", "trainer.max_time=null",
                     "trainer.max_steps=2", *FAST_TRAIN)
    shutil.copytree(dataset.parent, tmp_path / "copy")
    data = tmp_path / "copy" / dataset.name
    manifest = json.loads((data / "manifest.json").read_text())
    manifest["categories"] = manifest["categories"][::-1]
    (data / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match=r"trained on \d+ categories that differ from the \d+ of .*manifest.json "
                                         r"\(first at column 0"):
        sample_in_process(f"ckpt={out / 'checkpoints' / 'last.ckpt'}", f"data.root={data}",
                          f"out_dir={tmp_path / 's'}", "renders=0")
    assert not (tmp_path / "s" / "scenes").exists() or not list((tmp_path / "s" / "scenes").iterdir())


def test_a_manifest_whose_category_list_lacks_a_used_category_is_named_before_training_starts(dataset, tmp_path):
    from spread.data import SceneDataset

    shutil.copytree(dataset.parent, tmp_path / "copy")
    data = tmp_path / "copy" / dataset.name
    manifest = json.loads((data / "manifest.json").read_text())
    assert len(SceneDataset(data, "train")) > 0  # the dataset as written is accepted
    from spread.scene import read_scene

    first = next(iter(sorted((data / "train").glob("*.npz"))))
    dropped = str(read_scene(first).category[0])
    manifest["categories"] = [c for c in manifest["categories"] if c != dropped]
    (data / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match=rf"manifest.json: key 'categories' lacks '{dropped}'.*, used by .*\.npz"):
        SceneDataset(data, "train")


def test_an_import_whose_every_room_fails_on_its_assets_names_an_asset_not_none():
    from types import SimpleNamespace

    from spread.importers.run import first_failure

    rooms = SimpleNamespace(rooms=[SimpleNamespace(tag="r1"), SimpleNamespace(tag="r2")])
    scans = {"r1": {"error": None}, "r2": {"error": None}}
    assets = {"a7": {"tag": None, "file": "models/a7/raw_model.obj", "error": "no faces"}}
    assert first_failure(rooms, scans, assets) == {"tag": "an asset", "file": "models/a7/raw_model.obj",
                                                   "error": "no faces"}
    scans["r2"]["error"] = {"tag": "r2", "file": "r2.json", "error": "bad"}
    assert first_failure(rooms, scans, assets)["tag"] == "r2"
