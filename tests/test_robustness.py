"""Hostile and damaged input (docs/robustness.md): no code runs from a data file, resume notices changed or
broken files, late failures come early with a clear message, and a resumed training run is the same run.

Payloads in these tests only create a marker file; the marker must never appear.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from spread.safe_load import UnsafeFileError, load_checkpoint, load_npz
from spread.scene import SceneFormatError, list_scene_files, read_scene, write_scene

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset, train_in_process


class Payload:
    """Unpickling this object creates ``marker`` (what an attacker's ``os.system`` would do instead)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("robust"), rooms=12)


@pytest.fixture(scope="module")
def checkpoint(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("robustrun") / "run"
    train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null", "trainer.max_steps=2",
                     *SMALL_MODEL, *FAST_TRAIN)
    return out / "checkpoints" / "last.ckpt"


# ---- no code runs from a data file -----------------------------------------------------------------------

def test_a_checkpoint_carrying_a_pickled_payload_is_refused_and_runs_nothing(checkpoint, tmp_path):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.ckpt"
    data = torch.load(checkpoint, map_location="cpu", weights_only=True)
    data["hyper_parameters"]["note"] = Payload(marker)
    torch.save(data, evil)
    with pytest.raises(UnsafeFileError, match="evil.ckpt.*pickled"):
        load_checkpoint(evil)
    assert not marker.exists()
    assert load_checkpoint(checkpoint)["global_step"] == 2  # the platform's own checkpoints load as they are


def test_spread_sample_refuses_a_payload_checkpoint_before_any_work(dataset, checkpoint, tmp_path):
    from helpers import sample_in_process

    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.ckpt"
    data = torch.load(checkpoint, map_location="cpu", weights_only=True)
    data["state_dict"]["extra"] = Payload(marker)
    torch.save(data, evil)
    with pytest.raises(UnsafeFileError, match="evil.ckpt"):
        sample_in_process(f"ckpt={evil}", f"data.root={dataset}", f"out_dir={tmp_path / 'out'}")
    assert not marker.exists() and not list((tmp_path / "out" / "scenes").glob("*.npz"))


def test_a_truncated_checkpoint_gets_an_error_naming_the_file(checkpoint, tmp_path):
    cut = tmp_path / "cut.ckpt"
    cut.write_bytes(checkpoint.read_bytes()[: checkpoint.stat().st_size // 2])
    with pytest.raises(UnsafeFileError, match="cut.ckpt.*truncated or corrupt"):
        load_checkpoint(cut)


def test_a_checkpoint_in_torchs_legacy_format_loads_mapped_or_not_and_a_legacy_payload_is_refused(tmp_path):
    """A valid non-zip checkpoint (torch < 1.6, or ``_use_new_zipfile_serialization=False``) was refused as "truncated
    or corrupt" wherever it was memory-mapped (mmap needs the zip format): it is read whole instead."""
    legacy = tmp_path / "legacy.pth"
    torch.save({"model": {"a": torch.arange(3.0)}}, legacy, _use_new_zipfile_serialization=False)
    for mmap in (False, True):
        assert torch.equal(load_checkpoint(legacy, mmap=mmap)["model"]["a"], torch.arange(3.0))
    marker, evil = tmp_path / "pwned", tmp_path / "evil.pth"
    torch.save({"model": {"a": Payload(marker)}}, evil, _use_new_zipfile_serialization=False)
    with pytest.raises(UnsafeFileError, match="evil.pth.*pickled"):
        load_checkpoint(evil, mmap=True)
    assert not marker.exists()
    text = tmp_path / "text.ckpt"  # neither zip nor legacy: the legacy reader raised IndexError, named now
    text.write_bytes(b"retrained")
    for mmap in (False, True):
        with pytest.raises(UnsafeFileError, match="text.ckpt: not a readable checkpoint"):
            load_checkpoint(text, mmap=mmap)


def test_an_object_array_in_an_npz_is_refused_and_runs_nothing(dataset, tmp_path):
    marker = tmp_path / "pwned"
    source = list_scene_files(dataset / "test")[0]
    with np.load(source) as f:
        arrays = {k: f[k] for k in f.files}
    arrays["category"] = np.array([Payload(marker)] * len(arrays["category"]), dtype=object)
    evil = tmp_path / "evil.npz"
    np.savez(evil, **arrays)
    with pytest.raises((UnsafeFileError, SceneFormatError), match="evil.npz"):
        read_scene(evil)
    with load_npz(evil) as data, pytest.raises(UnsafeFileError, match="'category' is an object array"):
        data["category"]
    assert not marker.exists()


# ---- nothing is written outside the output folder, whatever an id says -----------------------------------

def _files_under(root: Path) -> set[Path]:
    return {p for p in root.rglob("*") if p.is_file()}


def test_hostile_scene_ids_only_name_files_inside_the_scenes_folder(dataset, checkpoint, tmp_path):
    from helpers import sample_in_process

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    hostile = ["../../../pwned_sample", str(tmp_path / "abs_pwned"), "sub/dir"]
    for path, scene_id in zip(list_scene_files(data / "test"), hostile):
        scene = read_scene(path)
        write_scene(scene.with_poses(scene.translation, scene.rotation, scene_id=scene_id), path)
    before = _files_under(tmp_path)
    out = tmp_path / "a" / "b" / "out"
    result = sample_in_process(f"ckpt={checkpoint}", f"data.root={data}", f"out_dir={out}", "renders=3")
    new = _files_under(tmp_path) - before
    assert new and all(out in p.parents for p in new)
    scenes = [p for p in new if p.suffix == ".npz" and "scenes" in p.parts]
    assert all(p.parent == out / "scenes" for p in scenes) and len(result.files) == len(scenes)
    assert not (tmp_path / "abs_pwned_k0.npz").exists() and not (out / "scenes" / "sub").exists()


def test_a_hostile_asset_id_keeps_its_geometry_cache_inside_the_library(dataset, tmp_path):
    from spread.assets import AssetLibrary

    lib_dir = tmp_path / "deep" / "assets"
    shutil.copytree(dataset / "assets", lib_dir)
    shutil.rmtree(lib_dir / "cache", ignore_errors=True)
    index = json.loads((lib_dir / "index.json").read_text())
    old_id = sorted(index["assets"])[0]
    hostile = "../../../pwned_asset"
    record = index["assets"].pop(old_id)
    index["assets"][hostile] = {**record, "asset_id": hostile}
    (lib_dir / "index.json").write_text(json.dumps(index))
    before = _files_under(tmp_path)
    library = AssetLibrary.load(lib_dir)
    library.geometry(hostile)
    new = _files_under(tmp_path) - before
    assert len(new) == 1 and next(iter(new)).parent == lib_dir / "cache"
    assert library.cache_path(hostile).exists() and not list(tmp_path.rglob("pwned_asset*"))


# ---- resume notices changed or broken files ----------------------------------------------------------------

def test_a_resumed_sampling_run_resamples_a_truncated_file(dataset, checkpoint, tmp_path):
    from helpers import sample_in_process

    out = tmp_path / "out"
    first = sample_in_process(f"ckpt={checkpoint}", f"data.root={dataset}", f"out_dir={out}")
    victim = first.files[0]
    intact = victim.read_bytes()
    victim.write_bytes(intact[: len(intact) // 3])  # a file cut short by something other than our atomic writes
    again = sample_in_process(f"ckpt={checkpoint}", f"data.root={dataset}", f"out_dir={out}")
    assert again.manifest["redone_unreadable"] == 1 and again.manifest["written_this_run"] == 1
    assert victim.read_bytes() == intact  # the same seeds, so the same scene again


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_a_resumed_evaluation_redoes_a_scene_whose_file_was_replaced(dataset, tmp_path):
    from spread.configs import compose
    from spread.commands.evaluate import evaluate

    scenes = tmp_path / "scenes"
    shutil.copytree(dataset / "test", scenes)
    overrides = [f"scenes={scenes}", f"reference={dataset}", f"out_dir={tmp_path / 'eval'}", "logger=none",
                 "protocol.stability_runs=1", "fid.enabled=false", "ray.num_cpus=2", "progress=false", "renders=0"]
    first = evaluate(compose("evaluate", overrides))
    victim = list_scene_files(scenes)[0]
    scene = read_scene(victim)
    moved = scene.with_poses(scene.translation * 0.7, scene.rotation)  # same name and id, other content
    write_scene(moved, victim)
    again = evaluate(compose("evaluate", overrides))
    run = again.metrics["run"]
    assert run["redone_input_changed"] == 1 and run["evaluated_this_run"] == 1
    assert run["skipped_as_done"] == len(list_scene_files(scenes)) - 1
    old = {r["scene_id"]: r for r in first.records}[victim.stem]
    new = {r["scene_id"]: r for r in again.records}[victim.stem]
    assert new["input_sha256"] != old["input_sha256"] and new["details"] != old["details"]


@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_a_relaunch_with_another_protocol_is_redone_and_records_its_own_config(dataset, tmp_path):
    from spread.configs import compose
    from spread.commands.evaluate import evaluate

    out = tmp_path / "eval"
    overrides = [f"scenes={dataset / 'test'}", f"reference={dataset}", f"out_dir={out}", "logger=none",
                 "protocol.stability_runs=1", "fid.enabled=false", "ray.num_cpus=2", "progress=false", "renders=0"]
    evaluate(compose("evaluate", overrides))
    assert "stability_steps: 100" in (out / ".hydra" / "config.yaml").read_text()
    evaluate(compose("evaluate", [*overrides, "protocol.stability_steps=50"]))
    assert "stability_steps: 50" in (out / ".hydra" / "config.yaml").read_text()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["protocol"]["stability_steps"] == 50
    assert metrics["redone_because"] == "changed: protocol.stability_steps"


# ---- late and silent failures come early -------------------------------------------------------------------

def test_training_without_a_val_or_train_split_is_refused_before_any_logger_or_step(dataset, tmp_path):
    """Refused before a logger opens its run (FAST_TRAIN's csv logger: no ``csv/`` folder; wandb's offline run was
    opened first, 7 s into a launch whose data.root did not exist)."""
    data = tmp_path / "data"
    shutil.copytree(dataset, data, ignore=shutil.ignore_patterns("val"))
    out = tmp_path / "run"
    with pytest.raises(ValueError, match=r"no scene files in .*val.*limit_val_batches=0"):
        train_in_process(out, "experiment=quick", f"data.root={data}", "trainer.max_steps=2", *SMALL_MODEL,
                         *FAST_TRAIN)
    assert not (out / "checkpoints").exists() and not (out / "csv").exists()
    with pytest.raises(ValueError, match=r"data.root=.*nowhere: no scene files in .*nowhere/train to train on"):
        train_in_process(out, "experiment=quick", f"data.root={tmp_path / 'nowhere'}", *SMALL_MODEL, *FAST_TRAIN)
    assert not (out / "csv").exists()
    # check_val_every_n_epoch=null validates too (every val_check_interval batches, across epochs)
    with pytest.raises(ValueError, match=r"no scene files in .*val, and the trainer validates"):
        train_in_process(out, "experiment=quick", f"data.root={data}", "trainer.check_val_every_n_epoch=null",
                         "+trainer.val_check_interval=2", *SMALL_MODEL, *FAST_TRAIN)
    assert not (out / "csv").exists()


def test_generate_refuses_zero_rooms_before_the_asset_library_and_warns_about_empty_splits(tmp_path):
    from spread.procgen.dataset import DatasetConfig, check_config, generate_dataset

    with pytest.raises(ValueError, match="rooms=0"):
        generate_dataset(tmp_path / "zero", DatasetConfig(rooms=0), progress=False)
    assert not (tmp_path / "zero" / "assets").exists()
    warnings = check_config(DatasetConfig(rooms=8))
    assert len(warnings) == 2 and "val split no rooms" in warnings[0] and "test split no rooms" in warnings[1]
    assert check_config(DatasetConfig(rooms=10)) == []


def test_spread_evaluate_fails_when_nothing_could_be_evaluated(dataset, tmp_path):
    from helpers import run_script

    empty = tmp_path / "empty"
    empty.mkdir()
    proc = run_script("spread-evaluate", f"scenes={empty}", f"reference={dataset}", f"out_dir={tmp_path / 'a'}",
                      "logger=none", ok=False)
    assert proc.returncode != 0 and "no scene files" in proc.stderr
    bad = tmp_path / "bad"
    bad.mkdir()
    scene = read_scene(list_scene_files(dataset / "test")[0])
    scene.asset_id = np.array(["no_such_asset"] * scene.num_objects)
    write_scene(scene, bad / f"{scene.scene_id}.npz", validate=False)
    proc = run_script("spread-evaluate", f"scenes={bad}", f"reference={dataset}", f"out_dir={tmp_path / 'b'}",
                      "logger=none", "fid.enabled=false", "ray.num_cpus=1", ok=False)
    assert proc.returncode != 0 and "none of the 1 scenes could be evaluated" in proc.stderr
    assert json.loads((tmp_path / "b" / "metrics.json").read_text())["n_failed"] == 1


def test_two_graphs_with_one_scene_id_are_refused_naming_both_files():
    from spread.sampling.plan import Graph, plan_batches

    graphs = [Graph("kitchen", "/a/kitchen.npz", 3), Graph("kitchen", "/b/other.npz", 4)]
    with pytest.raises(ValueError, match=r"'kitchen'.*/a/kitchen.npz.*/b/other.npz"):
        plan_batches(graphs, 1, 2, 0)


def test_a_support_cycle_is_refused_with_the_cycle(dataset, tmp_path):
    scene = read_scene(list_scene_files(dataset / "test")[0])
    scene.physical = np.zeros_like(scene.physical)
    scene.physical[0, scene.num_objects - 1] = scene.physical[scene.num_objects - 1, 0] = 1
    with pytest.raises(SceneFormatError, match=rf"support cycle 0 → {scene.num_objects - 1} → 0"):
        write_scene(scene, tmp_path / "cycle.npz")


# ---- a resumed training run is the same run --------------------------------------------------------------

def test_a_training_run_stopped_mid_epoch_and_resumed_equals_the_uninterrupted_run(dataset, tmp_path):
    """Dropout and graph dropout on, 6 train rooms at batch 4 (2 batches an epoch): stopped after step 3
    (mid-epoch) and resumed to step 7, the weights and EMA equal the uninterrupted run's bit for bit."""
    common = ["experiment=quick", f"data.root={dataset}", "trainer.max_time=null", *SMALL_MODEL, *FAST_TRAIN,
              "model.config.dropout=0.1", "model.graph_dropout=0.3", "trainer.check_val_every_n_epoch=1"]
    whole = train_in_process(tmp_path / "whole", *common, "trainer.max_steps=7")
    train_in_process(tmp_path / "part", *common, "trainer.max_steps=3")
    resumed = train_in_process(tmp_path / "part", *common, "trainer.max_steps=7", "ckpt_path=last")
    assert whole["global_step"] == resumed["global_step"] == 7
    a = load_checkpoint(tmp_path / "whole" / "checkpoints" / "last.ckpt")["state_dict"]
    b = load_checkpoint(tmp_path / "part" / "checkpoints" / "last.ckpt")["state_dict"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert whole["metrics"]["train/loss"] == resumed["metrics"]["train/loss"]
    assert os.path.exists(tmp_path / "part" / ".hydra" / "config.yaml")


def test_an_augmented_epoch_draws_distinct_room_symmetry_pairs_in_a_resumable_order():
    from spread.data.order import EpochOrder

    rooms = 10
    order = EpochOrder(8 * rooms, seed=3, per_epoch=rooms)
    first = list(order)
    assert len(first) == len(order) == rooms and len(set(first)) == rooms and max(first) < 8 * rooms
    assert list(order) != first  # the next epoch draws other pairs
    resumed = EpochOrder(8 * rooms, seed=3, position=lambda: (0, 4), per_epoch=rooms)
    assert list(resumed) == first[4:]  # mid-epoch resume continues the same epoch's order
    with pytest.raises(ValueError, match="per_epoch"):
        EpochOrder(5, seed=0, per_epoch=6)


@pytest.mark.parametrize("text, problem", [("[1, 2]", "expected a JSON object, got list"),
                                           ('{"version": ', "not valid JSON")])
def test_damaged_json_files_are_refused_naming_the_file(tmp_path, text, problem):
    from spread.assets import AssetLibrary
    from spread.data.stats import StatsError, load_stats
    from spread.importers.threed_front import ROOM_TYPES, ThreedFront

    (tmp_path / "index.json").write_text(text)
    with pytest.raises(ValueError, match=f"index.json: {problem}"):
        AssetLibrary.load(tmp_path)
    (tmp_path / "stats.json").write_text(text)
    with pytest.raises(StatsError, match=f"stats.json: {problem}"):
        load_stats(tmp_path / "stats.json")
    (tmp_path / "dataset_stats.txt").write_text(text)
    with pytest.raises(ValueError, match=f"dataset_stats.txt: {problem}"):
        ThreedFront(tmp_path, splits=tmp_path / "splits.csv", room_type=ROOM_TYPES[0])
