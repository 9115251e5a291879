"""Hostile and damaged inputs, round 3 (docs/robustness.md, issue 26): nothing hangs, nothing poisons an
aggregate, one bad file never stops a run, every refusal names its file, checkpoints load under one policy,
run folders are the platform's.

Payloads in these tests only create a marker file; the marker must never appear.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

from spread.io import InputFileError, check_input_file, file_sha256
from spread.scene import (ImplausibleSceneError, SceneFormatError, list_scene_files, load_npz_arrays, read_scene,
                          write_scene)

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset, train_in_process


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("hostile"), rooms=12)


@pytest.fixture(scope="module")
def checkpoint(dataset, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("hostilerun") / "run"
    train_in_process(out, "experiment=quick", f"data.root={dataset}", "trainer.max_time=null", "trainer.max_steps=2",
                     *SMALL_MODEL, *FAST_TRAIN)
    return out / "checkpoints" / "last.ckpt"


class within:
    """Fail (instead of hanging the suite) when the block takes longer than ``seconds``."""

    def __init__(self, seconds: int):
        self.seconds = seconds

    def __enter__(self):
        def expire(*_):
            raise TimeoutError(f"still running after {self.seconds} s")

        self.old = signal.signal(signal.SIGALRM, expire)
        signal.alarm(self.seconds)
        self.started = time.perf_counter()
        return self

    def __exit__(self, *exc):
        signal.alarm(0)
        signal.signal(signal.SIGALRM, self.old)
        self.elapsed = time.perf_counter() - self.started


def write_zip_not_npz(path: Path) -> None:
    """A zip whose members carry the scene keys' names but are not ``.npy`` files (numpy returns raw bytes)."""
    with zipfile.ZipFile(path, "w") as z:
        for key in ("scene_id", "asset_id", "category", "translation", "rotation", "spatial", "physical"):
            z.writestr(key, b"not an array")


def hostile_files(folder: Path, good) -> dict[str, str]:
    """Plant every kind of bad scene file in ``folder``; returns file stem → words its error must hold."""
    (folder / "zero.npz").symlink_to("/dev/zero")
    os.mkfifo(folder / "fifo.npz")
    write_zip_not_npz(folder / "zipped.npz")
    far = good.with_poses(good.translation.copy(), good.rotation, scene_id="far")
    far.translation[0, 0] = 1e30
    write_scene(far, folder / "far.npz", validate=False)
    away = good.with_poses(good.translation + np.float32([2e5, 0, 0]), good.rotation, scene_id="away")
    write_scene(away, folder / "away.npz", validate=False)
    return {"zero": "symbolic link to /dev/zero", "fifo": "FIFO", "zipped": "not an .npz of arrays",
            "far": "implausible", "away": "beyond ±1000 m"}


# ---- 1. bounded reading ----------------------------------------------------------------------------------

def test_a_dev_zero_link_a_fifo_and_an_oversized_file_are_refused_by_name_within_a_second(tmp_path, monkeypatch):
    (tmp_path / "zero.npz").symlink_to("/dev/zero")
    os.mkfifo(tmp_path / "fifo.npz")
    with within(5) as clock:
        with pytest.raises(InputFileError, match=r"zero.npz: a symbolic link to /dev/zero, outside"):
            check_input_file(tmp_path / "zero.npz", root=tmp_path)
        with pytest.raises(InputFileError, match=r"zero.npz: not a regular file \(a character device\)"):
            file_sha256(tmp_path / "zero.npz")  # what spread-evaluate hashed for ever
        with pytest.raises(InputFileError, match=r"fifo.npz: not a regular file \(a FIFO"):
            file_sha256(tmp_path / "fifo.npz")
        with pytest.raises(SceneFormatError, match=r"zero.npz.*symbolic link to /dev/zero"):
            read_scene(tmp_path / "zero.npz")
    assert clock.elapsed < 1.0
    big = tmp_path / "big.npz"
    big.write_bytes(b"\0" * (3 << 20))
    monkeypatch.setenv("SPREAD_MAX_INPUT_MB", "2")
    with pytest.raises(InputFileError, match=r"big.npz: 3.0 MB, over the 2 MB limit.*SPREAD_MAX_INPUT_MB"):
        check_input_file(big)
    monkeypatch.setenv("SPREAD_MAX_INPUT_MB", "4")
    assert check_input_file(big) == big
    inside = tmp_path / "inside.npz"
    inside.symlink_to(big)  # a link that stays in its folder is followed
    assert check_input_file(inside, root=tmp_path) == inside


def test_a_compressed_npz_that_unpacks_past_the_input_limit_is_refused_before_it_is_unpacked(dataset, tmp_path,
                                                                                              monkeypatch):
    """np.savez_compressed packs zeros a thousandfold: a 2.9 MB file read its 3 GB in full (only the file on disk was
    limited). The limit now holds for the arrays as the archive's headers give their sizes, in every reader of .npz
    (scenes: sampling, training, evaluation, export, the viewer; the importers' rooms)."""
    from spread.safe_load import UnsafeFileError, load_npz

    arrays = load_npz_arrays(list_scene_files(dataset / "test")[0])
    bomb = tmp_path / "bomb.npz"
    np.savez_compressed(bomb, **arrays, junk=np.zeros(5 << 20, np.uint8))  # 5 MB unpacked, ~5 kB packed
    assert bomb.stat().st_size < 1 << 20
    monkeypatch.setenv("SPREAD_MAX_INPUT_MB", "2")
    with pytest.raises(UnsafeFileError, match=r"bomb.npz: its arrays unpack to 5\.\d MB \(key 'junk': 5\.0 MB\), over "
                                              r"the 2 MB limit.*SPREAD_MAX_INPUT_MB"):
        load_npz(bomb)
    with pytest.raises(SceneFormatError, match=r"bomb.npz.*key 'junk': 5\.0 MB\), over the 2 MB limit"):
        read_scene(bomb)
    with pytest.raises(SceneFormatError, match=r"bomb.npz.*over the 2 MB limit"):
        load_npz_arrays(bomb)
    monkeypatch.setenv("SPREAD_MAX_INPUT_MB", "8")  # under a limit that allows it, it reads as before
    assert read_scene(bomb).num_objects == read_scene(list_scene_files(dataset / "test")[0]).num_objects


def test_a_zip_that_is_not_an_npz_is_refused_naming_the_file(tmp_path):
    write_zip_not_npz(tmp_path / "zipped.npz")
    with pytest.raises(SceneFormatError, match=r"zipped.npz.*not an .npz of arrays"):
        read_scene(tmp_path / "zipped.npz")


# ---- 2. physical plausibility at the door -------------------------------------------------------------------

def test_absurd_positions_and_sizes_are_refused_by_name_and_the_bounds_can_be_changed(dataset, tmp_path, monkeypatch):
    from spread.assets import AssetLibrary

    library = AssetLibrary.load(dataset / "assets")
    good = read_scene(list_scene_files(dataset / "test")[0], assets=library)
    far = good.with_poses(good.translation.copy(), good.rotation)
    far.translation[1, 2] = 1e30
    with pytest.raises(ImplausibleSceneError, match=r"far.npz: key 'translation': object 1 .* beyond ±1000 m"):
        write_scene(far, tmp_path / "far.npz")
    away = good.with_poses(good.translation + np.float32([500, 0, 0]), good.rotation)
    write_scene(away, tmp_path / "away.npz", validate=False)
    with pytest.raises(ImplausibleSceneError, match=r"away.npz: key 'translation'.*more than 10 m outside the room"):
        read_scene(tmp_path / "away.npz")
    monkeypatch.setenv("SPREAD_MAX_COORDINATE_M", "1e6")
    monkeypatch.setenv("SPREAD_ROOM_MARGIN_M", "1e6")
    assert read_scene(tmp_path / "away.npz").num_objects == good.num_objects  # a bound is a setting
    monkeypatch.delenv("SPREAD_MAX_COORDINATE_M")
    monkeypatch.delenv("SPREAD_ROOM_MARGIN_M")
    aid = str(good.asset_id[0])
    library.records[aid].extents = np.array([1000.0, 0.1, 0.1])  # a mug scaled to 1 km
    with pytest.raises(ImplausibleSceneError, match=rf"asset '{aid}' is \[1000.0, 0.1, 0.1\] m across.*"
                                                    rf"SPREAD_MAX_EXTENT_M"):
        good.validate(assets=library)


def test_evaluation_records_every_bad_file_by_name_and_the_asd_stays_the_mean_of_the_plausible_scenes(
        dataset, tmp_path):
    """A /dev/zero link, a FIFO, a zip that is not an npz, a coordinate at 1e30 and a room 200 km away in one
    scenes folder: the run finishes, names each file with its reason, and every metric is the one of the
    good scenes alone (before: the run hung hashing /dev/zero; with the 1e30 scene alone ASD was 5.8e32 mm)."""
    from spread.configs import compose
    from spread.evaluation.aggregate import summary_values
    from spread.evaluation.protocol import EvalProtocol
    from spread.commands.evaluate import evaluate

    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for path in list_scene_files(dataset / "test")[:2]:
        shutil.copy(path, scenes / path.name)
    good = sorted(p.stem for p in list_scene_files(scenes))
    expected = hostile_files(scenes, read_scene(list_scene_files(dataset / "test")[0]))
    overrides = [f"scenes={scenes}", f"reference={dataset}", f"out_dir={tmp_path / 'eval'}", "logger=none",
                 "protocol.stability_runs=1", "fid.enabled=false", "ray.num_cpus=1", "chunk_size=8", "progress=false",
                 "renders=0", "bootstrap_resamples=0"]
    with within(300):
        result = evaluate(compose("evaluate", overrides))
    m = result.metrics
    failed = {f["scene_id"]: f["error"] for f in m["failed"]}
    assert set(failed) == set(expected)
    for stem, words in expected.items():
        assert f"{stem}.npz" in failed[stem] and words in failed[stem], failed[stem]
    assert m["n_evaluated"] == len(good) and m["n_implausible"] == 2 and m["n_refused_inputs"] == 2
    alone = summary_values([r for r in result.records if r["scene_id"] in good], EvalProtocol())
    for name in EvalProtocol().metrics:
        assert m[name] == alone[name]
    assert m["asd"] is not None and 0 <= m["asd"] < 1.0  # metres: a plausible support distance


def test_a_mean_over_scenes_never_absorbs_a_non_finite_or_damaged_record(dataset, tmp_path):
    from spread.evaluation.aggregate import summary_values
    from spread.evaluation.protocol import EvalProtocol
    from spread.evaluation.work import evaluate_scene, worker_library

    protocol = EvalProtocol(stability_runs=1)
    library = worker_library(str(dataset / "assets"))
    records = [evaluate_scene(p, library, protocol) for p in list_scene_files(dataset / "test")[:2]]
    clean = summary_values(records, protocol)
    poisoned = json.loads(json.dumps(records[1]))
    poisoned["scene_id"] = "poisoned"
    poisoned["state"]["asd"] = {k: None for k in poisoned["state"]["asd"]}  # a NaN after finite_or_none
    mangled = json.loads(json.dumps(records[1]))
    mangled["scene_id"] = "mangled"
    del mangled["state"]["grecall"]
    mixed = summary_values([*records, poisoned, mangled], protocol)
    assert mixed["asd"] == clean["asd"] and mixed["grecall"] == clean["grecall"]
    assert mixed["n_evaluated"] == 2 and mixed["n_failed"] == 2


# ---- 3. one bad file never stops a run ----------------------------------------------------------------------

def test_a_zip_that_is_not_an_npz_in_test_and_train_is_named_skipped_and_the_rest_is_sampled_and_trained_on(
        dataset, checkpoint, tmp_path):
    """Before: spread-sample and spread-train stopped with AttributeError: 'bytes' object has no attribute
    'dtype', naming no file."""
    from helpers import sample_in_process

    data = tmp_path / "data"
    shutil.copytree(dataset, data)
    for split in ("test", "train"):
        write_zip_not_npz(data / split / "zipped.npz")
    result = sample_in_process(f"ckpt={checkpoint}", f"data.root={data}", f"out_dir={tmp_path / 'sample'}")
    good = len(list_scene_files(dataset / "test"))
    assert result.manifest["graphs"] == good and len(result.files) == good
    [skipped] = result.manifest["skipped_graphs"]
    assert skipped["file"] == str(data / "test" / "zipped.npz") and "not an .npz of arrays" in skipped["error"]
    summary = train_in_process(tmp_path / "run", "experiment=quick", f"data.root={data}", "trainer.max_time=null",
                               "trainer.max_steps=2", *SMALL_MODEL, *FAST_TRAIN)
    assert summary["global_step"] == 2
    [bad] = summary["skipped_scene_files"]["train"]
    assert bad["file"] == str(data / "train" / "zipped.npz")
    for path in list_scene_files(data / "val"):
        write_zip_not_npz(path)  # a split with no usable file is refused, naming it
    with pytest.raises(ValueError, match=r"val: none of its \d+ scene files is usable"):
        train_in_process(tmp_path / "run2", "experiment=quick", f"data.root={data}", "trainer.max_steps=2",
                         *SMALL_MODEL, *FAST_TRAIN)


# ---- 5. checkpoints under one policy --------------------------------------------------------------------------

class Payload:
    """Unpickling this object creates ``marker`` (what an attacker's ``os.system`` would do instead)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def edited_checkpoint(source: Path, target: Path, edit) -> Path:
    import torch

    data = torch.load(source, map_location="cpu", weights_only=True)
    edit(data)
    torch.save(data, target)
    return target


def test_spread_train_never_runs_a_payload_even_with_torch_force_no_weights_only_load(
        dataset, checkpoint, tmp_path, monkeypatch):
    """Before: Lightning's own load honoured TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1 and ran the payload."""
    from spread.safe_load import UnsafeFileError

    marker = tmp_path / "pwned"
    evil = edited_checkpoint(checkpoint, tmp_path / "evil.ckpt",
                             lambda d: d["callbacks"].__setitem__("evil", Payload(marker)))
    monkeypatch.setenv("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    common = ["experiment=quick", f"data.root={dataset}", "trainer.max_time=null", "trainer.max_steps=3",
              *SMALL_MODEL, *FAST_TRAIN]
    with pytest.raises(UnsafeFileError, match="evil.ckpt: refused"):
        train_in_process(tmp_path / "run", *common, f"ckpt_path={evil}")
    assert not marker.exists()
    from spread.training.checkpoints import atomic_checkpoint_io

    with pytest.raises(UnsafeFileError, match="evil.ckpt: refused"):  # Lightning's loader itself, on any path
        atomic_checkpoint_io().load_checkpoint(evil, weights_only=False)
    assert not marker.exists()
    cut = tmp_path / "cut.ckpt"
    cut.write_bytes(checkpoint.read_bytes()[: checkpoint.stat().st_size // 2])
    with pytest.raises(UnsafeFileError, match="cut.ckpt: not a readable checkpoint"):
        train_in_process(tmp_path / "run", *common, f"ckpt_path={cut}")
    assert train_in_process(tmp_path / "run", *common, f"ckpt_path={checkpoint}")["global_step"] == 3


def test_a_checkpoint_of_another_kind_or_size_is_refused_in_one_line_before_allocation(dataset, checkpoint, tmp_path):
    from helpers import sample_in_process

    from spread.experiments.ablation import AblationSpec
    from spread.experiments.compare import CompareSpec
    from spread.safe_load import CheckpointMismatchError

    atiss = edited_checkpoint(checkpoint, tmp_path / "atiss.ckpt",
                              lambda d: d["hyper_parameters"].update(method="atiss", variant=None))
    with pytest.raises(CheckpointMismatchError) as err:
        AblationSpec(out_dir=tmp_path / "ablate", data_root=dataset, ckpt={"geometry": str(atiss)})
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"train.ckpt.geometry={atiss}: a 'atiss' checkpoint")
    assert "expected method='spread', variant='geometry'" in message
    with pytest.raises(CheckpointMismatchError, match=r"train.ckpt.base=.*'spread' geometry.*expected variant='base'"):
        AblationSpec(out_dir=tmp_path / "ablate", data_root=dataset, ckpt={"base": str(checkpoint)})
    with pytest.raises(CheckpointMismatchError, match=r"train.ckpt.diffuscene=.*'spread'.*expected method='diffuscene'"):
        CompareSpec(out_dir=tmp_path / "compare", data_root=dataset, ckpt={"diffuscene": str(checkpoint)})
    wide = [o.replace("model.config.dim=32", "model.config.dim=48") for o in SMALL_MODEL]
    with pytest.raises(CheckpointMismatchError, match=r"ckpt_path=.*config.dim=32\); expected config.dim=48"):
        train_in_process(tmp_path / "run", "experiment=quick", f"data.root={dataset}", "trainer.max_steps=3", *wide,
                         *FAST_TRAIN, f"ckpt_path={checkpoint}")
    with pytest.raises(CheckpointMismatchError, match=r"model.init_from=.*'atiss'"):
        train_in_process(tmp_path / "run2", "experiment=quick", f"data.root={dataset}", "trainer.max_steps=1",
                         *SMALL_MODEL, *FAST_TRAIN, f"model.init_from={atiss}")
    huge = edited_checkpoint(checkpoint, tmp_path / "huge.ckpt",
                             lambda d: d["hyper_parameters"]["config"].update(dim=2_000_000))
    with within(20):  # before: an attempt to allocate ~600 TB
        with pytest.raises(CheckpointMismatchError, match=r"huge.ckpt: its hyperparameters build weight .* refused "
                                                          r"before allocating"):
            sample_in_process(f"ckpt={huge}", f"data.root={dataset}", f"out_dir={tmp_path / 'out'}")


# ---- 4. / 6. imports: a failing asset takes only its rooms, re-imports keep disk, manifest and splits equal ----

IMPORT_FAST = dict(processes=1, progress=False, renders=0, decomposition="hull", fidelity_samples=200)


def add_room_with_a_1e30_vertex(src: Path) -> str:
    """A fifth release room whose third object is asset Bad_9: a box mesh with one vertex at 1e30."""
    import trimesh

    import realdata

    box = trimesh.creation.box(extents=(0.2, 0.2, 0.2))
    vertices = np.asarray(box.vertices).copy()
    vertices[0] = [1e30, 0.1, 0.1]
    bad = trimesh.Scene()
    bad.add_geometry(trimesh.Trimesh(vertices, box.faces, process=False), node_name="bad")
    (src / "meshes" / "Bad_9_unpacked.glb").write_bytes(bad.export(file_type="glb"))
    tag = "ProcTHOR-Test-9-room|bad"
    (src / tag).mkdir()
    np.savez(src / tag / "boxes.npz", **realdata.release_boxes("rest", names=["Table_1", "Mug_3", "Bad_9"]))
    split = json.loads((src / "train_test_split.json").read_text())
    split["train"].append(tag)
    (src / "train_test_split.json").write_text(json.dumps(split))
    return tag


def test_an_import_with_a_mesh_vertex_at_1e30_writes_every_good_room_and_records_the_bad_asset(tmp_path):
    """Before: the asset imported, then the cache build raised QhullError and the whole import stopped
    (no manifest, no scene)."""
    import realdata
    from spread.importers.run import ImportConfig, import_dataset

    src = realdata.release_layout(tmp_path / "src")
    tag = add_room_with_a_1e30_vertex(src)
    out = tmp_path / "out"
    manifest = import_dataset(ImportConfig("spread_release", str(src), str(out), **IMPORT_FAST))
    assert sum(manifest["counts"].values()) == 4 == len(list(out.glob("*/*.npz")))  # the four good rooms
    [asset] = manifest["errors"]["assets"]
    assert asset["asset_id"] == "Bad_9" and asset["file"].endswith("Bad_9_unpacked.glb")
    assert "implausible" in asset["error"] or "Qhull" in asset["error"]
    [room] = manifest["errors"]["rooms"]
    assert room["tag"] == tag and "Bad_9" in room["error"]
    assert json.loads((out / "manifest.json").read_text())["failed_assets"] == 1
    from spread.assets import AssetLibrary

    assert "Bad_9" not in AssetLibrary.load(out / "assets").records


def test_a_reimport_removes_what_the_new_import_no_longer_has_and_warns_about_an_empty_val_split(tmp_path, capsys):
    """Before: a room moved from val to test stayed in val too (in two splits), the manifest's counts
    disagreed with the disk, and an empty val split was not mentioned."""
    import realdata
    from spread.importers.run import ImportConfig, import_dataset

    src = realdata.release_layout(tmp_path / "src")
    out = tmp_path / "out"
    first = import_dataset(ImportConfig("spread_release", str(src), str(out), **IMPORT_FAST))
    assert first["counts"] == {"train": 1, "val": 1, "test": 2} and first["warnings"] == []
    [val_file] = (out / "val").glob("*.npz")
    moved = str(read_scene(val_file).extras["source_tag"])
    split = json.loads((src / "train_test_split.json").read_text())
    split["train"].remove(moved)
    split["val"].append(moved)  # the release's val list is our test split
    (src / "train_test_split.json").write_text(json.dumps(split))
    again = import_dataset(ImportConfig("spread_release", str(src), str(out), **IMPORT_FAST))
    on_disk = {s: len(list((out / s).glob("*.npz"))) for s in ("train", "val", "test")}
    assert again["counts"] == on_disk and on_disk["test"] == 3 and not val_file.exists()
    stems = [p.stem for p in out.glob("*/*.npz")]
    assert len(stems) == len(set(stems))  # no room in two splits
    assert again["this_run"]["removed_stale"] == [f"val/{val_file.name}"]
    assert any("val split has no scenes" in w for w in again["warnings"])


def test_a_planted_link_at_the_import_log_is_refused_and_its_target_untouched(tmp_path):
    """Before: spread-import appended its room lines to whatever out_dir/import/rooms.jsonl pointed to."""
    import realdata
    from spread.importers.run import ImportConfig, import_dataset
    from spread.io import UnsafeOutputError, append_jsonl

    src = realdata.release_layout(tmp_path / "src")
    target = tmp_path / "precious.txt"
    target.write_text("keep me\n")
    out = tmp_path / "out"
    (out / "import").mkdir(parents=True)
    (out / "import" / "rooms.jsonl").symlink_to(target)
    with pytest.raises(UnsafeOutputError, match=r"rooms.jsonl: a symbolic link .*remove the link"):
        import_dataset(ImportConfig("spread_release", str(src), str(out), **IMPORT_FAST))
    with pytest.raises(UnsafeOutputError, match=r"rooms.jsonl: a symbolic link"):
        append_jsonl(out / "import" / "rooms.jsonl", {"tag": "x"})  # every append, not only the import's
    assert target.read_text() == "keep me\n" and not (out / "train").exists()


def test_hydras_command_log_replaces_a_planted_link_and_leaves_its_target_untouched(tmp_path):
    from helpers import run_script

    target = tmp_path / "precious.txt"
    target.write_text("keep me\n")
    out = tmp_path / "out"
    out.mkdir()
    (out / "report.log").symlink_to(target)
    run_script("spread-report", f"runs={tmp_path / 'none'}", f"out_dir={out}", ok=False)
    assert target.read_text() == "keep me\n"  # refused before it logged a line: the log was never opened
    import logging

    from spread.io import RunLogFileHandler

    handler = RunLogFileHandler(str(out / "report.log"), delay=True)  # as conf/hydra/default.yaml makes it
    handler.emit(logging.LogRecord("spread", logging.INFO, __file__, 1, "a line", None, None))
    handler.close()
    assert target.read_text() == "keep me\n"
    assert (out / "report.log").read_text() == "a line\n" and not (out / "report.log").is_symlink()


def test_a_command_refused_by_its_checks_leaves_no_empty_log_behind(tmp_path):
    from helpers import user_error

    out = tmp_path / "out"
    line, _ = user_error("spread-sample", f"ckpt={tmp_path / 'no.ckpt'}", f"data.root={tmp_path}", f"out_dir={out}")
    assert line.startswith("spread-sample: ") and "no such checkpoint file" in line
    assert not out.exists()  # Hydra made it and the run lock was taken: both gone (sample.log was never made)


def test_a_refused_command_removes_the_folders_its_out_dir_made_on_the_way_through_dot_dot(tmp_path):
    """``out_dir=a/../b`` (relative, as typed): creating it as written makes ``a`` too, which the normalised folder
    (``b``) does not name; it was left behind, empty. A folder that was there (``keep`` of ``keep/../c``) stays."""
    from helpers import user_error

    (tmp_path / "keep").mkdir()
    for out_dir in ("a/../b", "x/y/../../z/w/../q", "keep/../c"):
        line, _ = user_error("spread-sample", "ckpt=no.ckpt", f"data.root={tmp_path}", f"out_dir={out_dir}",
                             cwd=tmp_path)
        assert "no such checkpoint file" in line
        assert sorted(p.name for p in tmp_path.iterdir()) == ["keep"], out_dir


def test_an_out_dir_with_dot_dot_after_a_link_or_through_a_looping_or_dangling_link_is_refused_in_one_line(tmp_path):
    """``out_dir=link/../b`` with ``link`` → ``elsewhere/target``: the system makes ``b`` beside the link's target
    (``elsewhere/b``), while atomic writes' temporary files and Hydra's run folder go by the text (``./b``): a
    refused run left ``elsewhere/b`` with its lock, an evaluation failed on a missing ``./b`` or, where ``./b`` was
    another run's folder, wrote its log there. A link that loops or leads nowhere gave a traceback. ``++out_dir=``
    is checked as composed."""
    from helpers import user_error

    from spread.io import normal_path

    (tmp_path / "elsewhere" / "target").mkdir(parents=True)
    here = tmp_path / "here"
    here.mkdir()
    (here / "link").symlink_to(tmp_path / "elsewhere" / "target")
    (here / "loop").symlink_to("loop")
    (here / "dangling").symlink_to(tmp_path / "nowhere" / "x")
    assert normal_path(here / "link" / ".." / "b") == tmp_path / "elsewhere" / "b"
    assert normal_path(here / "link" / "x" / ".." / "..") == tmp_path / "elsewhere"
    assert normal_path(here / "a" / ".." / "b") == here / "b"
    for out_dir, says in [("link/../b", f"a '..' follows a symbolic link, so the system means {tmp_path}/elsewhere/b "
                                        f"while the text reads {here}/b; give the folder without '..' "
                                        f"(out_dir={tmp_path}/elsewhere/b)"),
                          ("link/x/../../e", f"the system means {tmp_path}/elsewhere/e"),
                          ("loop/b", "loop is a symbolic link that leads nowhere"),
                          ("dangling/b", f"dangling is a symbolic link that leads nowhere ({tmp_path}/nowhere/x)"),
                          ("dangling/../b", f"the system means {tmp_path}/nowhere/b")]:
        for name in ("spread-sample", "spread-generate") if out_dir == "link/../b" else ("spread-sample",):
            extra = ["ckpt=no.ckpt", f"data.root={tmp_path}"] if name == "spread-sample" else ["rooms=0"]
            line, _ = user_error(name, *extra, f"out_dir={out_dir}", cwd=here)
            assert line.startswith(f"{name}: out_dir={out_dir}: ") and says in line, line
            assert sorted(p.name for p in (tmp_path / "elsewhere").iterdir()) == ["target"], out_dir
            assert list((tmp_path / "elsewhere" / "target").iterdir()) == [], out_dir
            assert sorted(p.name for p in here.iterdir()) == ["dangling", "link", "loop"], out_dir
    line, _ = user_error("spread-sample", "ckpt=no.ckpt", f"data.root={tmp_path}", "++out_dir=link/../f", cwd=here)
    assert line.startswith(f"spread-sample: out_dir=link/../f: a '..' follows a symbolic link"), line  # as composed
    assert sorted(p.name for p in (tmp_path / "elsewhere").iterdir()) == ["target"]


def test_a_refused_command_leaves_nothing_at_its_default_folder_nor_hydras_record_of_a_dataset_command(tmp_path):
    """The cleanup read ``out_dir=`` from the command line: a refused ``spread-train`` at its default folder
    (``runs/train/<name>/<time>``, the README's form) left that folder and its lock, ``spread-generate`` left
    ``logs/generate/<time>/.hydra`` in the dataset folder, and ``spread-sample`` its empty ``scenes/``."""
    from helpers import user_error

    (tmp_path / "no_scenes").mkdir()
    line, _ = user_error("spread-train", "experiment=quick", f"data.root={tmp_path / 'no_scenes'}", cwd=tmp_path)
    assert "no scene files in" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["no_scenes"]  # no runs/train/quick/<time>
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "notes.txt").write_text("mine")
    line, _ = user_error("spread-generate", "rooms=0", f"out_dir={tmp_path / 'ds'}", cwd=tmp_path)
    assert "rooms=0" in line
    assert [p.name for p in (tmp_path / "ds").iterdir()] == ["notes.txt"]  # no logs/, no lock; its file kept


def test_a_refused_command_removes_only_the_folders_and_lock_it_made_and_nothing_it_found():
    import tempfile

    from spread.cli.errors import FolderLeftEmpty
    from spread.io import run_lock

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        new = FolderLeftEmpty.of(["data.root=/d", f"out_dir={tmp / 'a' / 'b'}"])
        with run_lock(tmp / "a" / "b", "spread-train"):
            pass
        new.remove()
        assert list(tmp.iterdir()) == []  # b, a and the lock: all made by the refused command
        (tmp / "kept").mkdir()
        (tmp / "kept" / "notes.txt").write_text("mine")
        found = FolderLeftEmpty.of([f"out_dir={tmp / 'kept'}"])
        with run_lock(tmp / "kept", "spread-train"):
            pass
        found.remove()
        assert [p.name for p in (tmp / "kept").iterdir()] == ["notes.txt"]  # kept, with what it held; the lock gone
        (tmp / "empty").mkdir()
        empty = FolderLeftEmpty.of([f"out_dir={tmp / 'empty'}"])
        with run_lock(tmp / "empty", "spread-train"):
            pass
        empty.remove()
        assert (tmp / "empty").is_dir() and list((tmp / "empty").iterdir()) == []  # there before: kept, lock gone
        with run_lock(tmp / "empty", "spread-train"):
            again = FolderLeftEmpty.of([f"out_dir={tmp / 'empty'}"])
            again.remove()  # another run holds the lock: left alone
            assert [p.name for p in (tmp / "empty").iterdir()] == [".spread.lock"]
        assert FolderLeftEmpty.of(["-m", f"out_dir={tmp / 'x'}", "seed=1,2"]).planned is None  # a multirun's own
        dotted = FolderLeftEmpty.of([f"++out_dir={tmp / 'n' / '..' / 'm' / 'r'}"])  # normalised: tmp/m/r
        with run_lock(tmp / "m" / "r", "spread-sample"):
            (tmp / "m" / "r" / "scenes" / "part").mkdir(parents=True)  # empty folders it made inside
        dotted.remove()
        assert sorted(p.name for p in tmp.iterdir()) == ["empty", "kept"]  # m, r, scenes, part and the lock gone


def test_a_console_main_called_in_process_leaves_no_noted_folder_for_a_later_cleanup(tmp_path):
    """A console script's ``main(cfg)`` called as a library (a test, a study's in-process stage) noted its run folder
    for the cleanup of a refused command and kept it: a later cleanup in the same process then looked at that
    stale folder instead of its own, and left its own folders behind (found by ``make test`` when another file's
    in-process evaluation ran before this file on the same worker)."""
    from spread.cli.errors import FolderLeftEmpty
    from spread.cli.sample import main
    from spread.configs import compose
    from spread.io import run_lock

    stale = tmp_path / "stale"
    with pytest.raises(BaseException, match="no such checkpoint file"):
        main(compose("sample", [f"ckpt={tmp_path / 'no.ckpt'}", f"data.root={tmp_path}", f"out_dir={stale}"]))
    new = FolderLeftEmpty.of([f"out_dir={tmp_path / 'a' / 'b'}"])
    with run_lock(tmp_path / "a" / "b", "spread-sample"):
        pass
    new.remove()
    assert not (tmp_path / "a").exists()  # its own folders and lock gone, whatever ran before it


def test_two_scene_files_with_one_inner_id_both_export(dataset, tmp_path):
    """Before: "2 written" was reported as 1 and the second file overwrote the first."""
    from spread.export import export_folder

    scenes = tmp_path / "scenes"
    scenes.mkdir()
    first, second = list_scene_files(dataset / "test")[:2]
    shutil.copy(first, scenes / "a.npz")
    twin = read_scene(second)
    write_scene(twin.with_poses(twin.translation, twin.rotation, scene_id=read_scene(first).scene_id), scenes / "b.npz")
    report = export_folder(scenes, dataset / "assets", tmp_path / "out", "mjcf")
    assert len(report.written) == 2 and not report.failed
    assert len({Path(p) for p in report.written.values()}) == 2 and all(Path(p).exists() for p in report.written.values())
    [(file, note)] = report.duplicates.items()
    assert file == str(scenes / "b.npz") and str(scenes / "a.npz") in note
    assert json.loads((tmp_path / "out" / "export.json").read_text())["n_written"] == 2


def test_two_evaluations_of_one_folder_never_share_a_metrics_json(dataset, tmp_path):
    """A run folder is locked while a run writes it: a second evaluation (another protocol) is refused at once,
    naming the running one, and writes nothing (before: with no lock, a MuJoCo 3-run evaluation's
    metrics.json carried the pybullet 1-run number)."""
    import subprocess
    import sys

    from spread.configs import compose
    from spread.commands.evaluate import evaluate
    from spread.io import RunFolderBusy

    out = tmp_path / "eval"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nfrom spread.io import run_lock\n"
        f"with run_lock({str(out)!r}, 'spread-evaluate'):\n    print('held', flush=True)\n    time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        common = [f"scenes={dataset / 'test'}", f"reference={dataset}", f"out_dir={out}", "logger=none",
                  "fid.enabled=false", "ray.num_cpus=2", "progress=false", "renders=0", "bootstrap_resamples=0"]
        with within(10), pytest.raises(RunFolderBusy, match=rf"eval: in use by a running spread-evaluate \(pid "
                                                              rf"{holder.pid}"):
            evaluate(compose("evaluate", [*common, "protocol.stability_runs=3"]))
    finally:
        holder.kill()
        holder.wait()
    assert not (out / "metrics.json").exists() and not (out / "per_scene.jsonl").exists()
    train_dir = tmp_path / "run"
    holder = subprocess.Popen([sys.executable, "-c", (
        "import sys, time\nfrom spread.io import run_lock\n"
        f"with run_lock({str(train_dir)!r}, 'spread-train'):\n    print('held', flush=True)\n    time.sleep(60)")],
        stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        with pytest.raises(RunFolderBusy, match=r"run: in use by a running spread-train"):
            train_in_process(train_dir, "experiment=quick", f"data.root={dataset}", "trainer.max_steps=1",
                             *SMALL_MODEL, *FAST_TRAIN)
    finally:
        holder.kill()
        holder.wait()
    assert not (train_dir / "checkpoints").exists() and not (train_dir / ".hydra").exists()
    # once the folder is free, a run of another protocol redoes it from scratch (check_protocol)
    # (test_robustness.py::test_a_relaunch_with_another_protocol_is_redone_and_records_its_own_config)


# ---- 7. reports -----------------------------------------------------------------------------------------------

def test_a_hand_edited_text_metric_is_shown_invalid_never_with_an_interval():
    """Before: spread-report printed a hand-edited "grecall": "abc" as "abc ± 0.125"."""
    from spread.reporting.tables import metric_columns

    METRICS = metric_columns()

    grecall = next(c for c in METRICS if c.key == "grecall")
    record = {"grecall": "abc", "grecall_lo": 0.5, "grecall_hi": 0.75}
    assert grecall.cell(record) == "invalid ('abc')" and grecall.cell(record, latex=True) == "invalid ('abc')"
    assert grecall.cell({"grecall": 0.6, "grecall_lo": 0.5, "grecall_hi": 0.75}) == "0.600 ± 0.125"


# ---- 8. bounded sampling ----------------------------------------------------------------------------------------

def test_a_graph_above_the_object_limit_is_skipped_by_name_before_any_work_and_the_others_are_sampled(
        dataset, checkpoint, tmp_path):
    """The 400-object graph (before: no scene after 10 minutes, and the 7-object graph of its batch blocked
    with it), tested with the limit: every graph above ``max_objects`` is named and the rest sampled."""
    from helpers import sample_in_process

    from spread.sampling.run import object_limit

    sizes = {p: read_scene(p).num_objects for p in list_scene_files(dataset / "test")}
    limit = sorted(sizes.values())[len(sizes) // 2]
    big = sorted(str(p) for p, n in sizes.items() if n > limit)
    assert big and len(big) < len(sizes)
    result = sample_in_process(f"ckpt={checkpoint}", f"data.root={dataset}", f"out_dir={tmp_path / 'out'}",
                               f"max_objects={limit}", "batch_size=8")
    skipped = {s["file"]: s["error"] for s in result.manifest["skipped_graphs"]}
    assert sorted(skipped) == big and all(f"over the object limit {limit}" in e for e in skipped.values())
    assert result.manifest["graphs"] == len(sizes) - len(big) == len(result.written)
    stats = json.loads((dataset / "stats.json").read_text())
    assert object_limit(dataset, None) == 2 * stats["max_objects"] and object_limit(dataset, 0) is None


def test_a_sample_pushed_kilometres_away_is_written_as_made_named_and_the_run_goes_on(dataset, checkpoint, tmp_path,
                                                                                      monkeypatch):
    """One sample beyond ±1000 m (before: the writer refused it and the whole run ended, and every relaunch ended
    the same way): the run finishes, the file is there as the model made it, sampling.json names it with why, the
    renders skip it, and a relaunch keeps it (sampling it again gives the same) and names it again."""
    from helpers import sample_in_process

    import spread.sampling.worker as worker

    made = worker.generated_scene
    far = []

    def pushed(source, translation, rotation, item, provenance, trajectory=None):
        if not far:  # the run's first sample: five kilometres east
            far.append(item.name)
            translation = translation + np.array([5000.0, 0.0, 0.0])
        return made(source, translation, rotation, item, provenance, trajectory)

    monkeypatch.setattr(worker, "generated_scene", pushed)
    out = tmp_path / "run"
    args = (f"ckpt={checkpoint}", f"data.root={dataset}", f"out_dir={out}", "renders=3", "sampler.steps=2")
    result = sample_in_process(*args)
    name = far[0]
    assert sorted(result.written) == sorted(p.stem for p in result.files) and name in result.written
    assert list(result.manifest["implausible"]) == [name] and "beyond ±1000 m" in result.manifest["implausible"][name]
    with pytest.raises(ImplausibleSceneError, match="beyond ±1000 m"):
        read_scene(out / "scenes" / f"{name}.npz")  # every reader refuses it; spread-evaluate counts it apart
    assert len(result.manifest["renders"]) == 2 and not (out / "renders" / f"{name}.png").exists()  # of 3
    again = sample_in_process(*args)
    assert again.written == [] and again.manifest["redone_unreadable"] == 0
    assert list(again.manifest["implausible"]) == [name]
    # a file a worker wrote but never reported (it died after writing it) is found on disk all the same
    from spread.sampling.run import unreported_implausible

    others = sorted(p.stem for p in (out / "scenes").glob("*.npz") if p.stem != name)
    assert unreported_implausible([name, *others], out / "scenes") == {name: again.manifest["implausible"][name]}


# ---- 9. user errors in one line, no noise -------------------------------------------------------------------------

def run_quietly(name: str, *args: str, timeout: int = 300):
    """A console script as a user runs it: no HYDRA_FULL_ERROR, wandb disabled."""
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "SPREAD_DEBUG")}
    env["WANDB_MODE"] = "disabled"
    return subprocess.run([str(Path(sys.executable).parent / name), *args], env=env, capture_output=True, text=True,
                          timeout=timeout)


def test_bad_settings_end_in_one_line_before_any_work(tmp_path, monkeypatch):
    """Before: room.max_objects=0 failed with "low >= high" after the asset library was built; an out_dir that
    is a file stopped with a traceback from inside Hydra."""
    from spread.cli.errors import out_dir_problem
    from spread.procgen.dataset import DatasetConfig, generate_dataset
    from spread.procgen.room_types import RoomConfig

    with pytest.raises(ValueError, match=r"room.max_objects=0"):
        generate_dataset(tmp_path / "zero", DatasetConfig(rooms=4, room=RoomConfig(max_objects=0)), progress=False)
    assert not (tmp_path / "zero" / "assets").exists()
    proc = run_quietly("spread-generate", f"out_dir={tmp_path / 'gen'}", "rooms=4", "room.max_objects=0")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 1 and "Traceback" not in proc.stderr and len(lines) == 1, proc.stderr
    assert lines[0].startswith("spread-generate: room.min_objects=2, room.max_objects=0")
    afile = tmp_path / "afile"
    afile.write_text("not a folder")
    proc = run_quietly("spread-evaluate", f"scenes={tmp_path}", f"reference={tmp_path}", f"out_dir={afile}")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.strip() == f"spread-evaluate: out_dir={afile}: exists and is not a folder; give a folder path"
    monkeypatch.setattr(os, "access", lambda path, mode: False)  # a read-only file system, as root cannot chmod away
    assert "not writable" in out_dir_problem(str(tmp_path))
    assert "cannot be created" in out_dir_problem(str(tmp_path / "new" / "run"))


def test_a_device_this_process_cannot_use_is_refused_in_one_line_before_any_sample(dataset, checkpoint, tmp_path,
                                                                                   monkeypatch):
    """Before: ``spread-sample device=cuda`` on a machine without a GPU, or ``device=gpu``, ended in torch's traceback
    from inside the model's loading, after the progress bar and the run's sampling.json were written; ``device=cuda
    workers=2`` without ``ray.num_gpus_per_worker`` started Ray workers that each saw no GPU."""
    import torch

    from spread.sampling.worker import resolve_device

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == "cpu" and resolve_device("cpu") == "cpu"
    with pytest.raises(ValueError, match=r"device='cuda': this process sees no CUDA device"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == "cuda" and resolve_device("cuda:1") == "cuda:1"
    with pytest.raises(ValueError, match=r"device='cuda:2': this process sees 2 CUDA device\(s\) \(cuda:0..cuda:1\)"):
        resolve_device("cuda:2")
    monkeypatch.undo()
    out = tmp_path / "out"
    proc = run_quietly("spread-sample", f"ckpt={checkpoint}", f"data.root={dataset}", f"out_dir={out}", "device=gpu",
                       "workers=0", "logger=none", "renders=0", "figures=0")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()]  # one line: no progress bar before it
    assert proc.stderr.startswith("spread-sample: device='gpu' is not a torch device (auto, cpu, cuda, cuda:N)")
    assert not (out / "sampling.json").exists() and not (out / "scenes").exists()
    from helpers import sample_in_process

    with pytest.raises(ValueError, match=r"device=cuda with workers=2: Ray gives a worker no GPU unless it asks for "
                                         r"one; set ray.num_gpus_per_worker=1"):  # each would see none: before Ray
        sample_in_process(f"ckpt={checkpoint}", f"data.root={dataset}", f"out_dir={out}", "device=cuda", "workers=2")
    assert not (out / "sampling.json").exists() and not (out / "scenes").exists()
    # a finished run's folder is left as it was (its scenes were deleted, then a traceback): another device type,
    # GPUs for Ray's workers on a machine without one
    (out / "scenes").mkdir(parents=True)
    (out / "scenes" / "kept_k0.npz").write_bytes(b"a finished run's scene")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for extra, words in [(["device=mps", "workers=0"], r"device='mps': the samplers run on auto, cpu, cuda or cuda:N"),
                         (["device=mps", "workers=2"], r"device='mps': the samplers run on auto, cpu, cuda or cuda:N"),
                         (["device=auto", "workers=2", "ray.num_gpus_per_worker=1"],
                          r"ray.num_gpus_per_worker=1.0 with workers=2: this machine has no GPU for the Ray")]:
        with pytest.raises(ValueError, match=words):
            sample_in_process(f"ckpt={checkpoint}", f"data.root={dataset}", f"out_dir={out}", *extra)
        assert (out / "scenes" / "kept_k0.npz").read_bytes() == b"a finished run's scene", extra


def test_a_model_setting_refused_inside_hydras_instantiate_and_a_gpu_trainer_without_a_gpu_end_in_one_line(
        dataset, tmp_path, monkeypatch):
    """Before: a ValueError from the model's constructor came wrapped in Hydra's four-line "Error in call to target"
    message, and ``trainer=gpu`` on a machine without a GPU in Lightning's "No supported gpu backend found!" after the
    data and the model were built."""
    import torch
    from hydra.errors import InstantiationException

    from spread.cli.errors import user_error
    from spread.training.fit import check_accelerator

    try:
        raise InstantiationException("Error in call to target 'x'") from ValueError("model.x must be 1")
    except InstantiationException as wrapped:
        assert str(user_error(wrapped)) == "model.x must be 1"
    try:
        raise InstantiationException("Error in call to target 'x'") from RuntimeError("a bug, not a setting")
    except InstantiationException as wrapped:
        assert user_error(wrapped) is None  # a bug keeps its traceback
    proc = run_quietly("spread-train", "experiment=quick", f"data.root={dataset}", f"out_dir={tmp_path / 'a'}",
                       "model.compile_bucket=0", "logger=none")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr and "Error in call" not in proc.stderr, proc.stderr
    assert proc.stderr.strip() == ("spread-train: model.compile_bucket must be an integer >= 1 (objects), got 0 "
                                   "(HYDRA_FULL_ERROR=1 shows the traceback)")
    from spread.configs import compose

    gpu = compose("train", ["trainer=gpu"])
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    check_accelerator(gpu)  # a GPU is there: nothing to say
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="trainer.accelerator=gpu .trainer=gpu.: this process sees no CUDA device"):
        check_accelerator(gpu)
    check_accelerator(compose("train", []))  # the CPU trainer: nothing to say
    check_accelerator(gpu, "cpu")  # a launcher's CPU workers (Ray Train without use_gpu): nothing to say
    monkeypatch.undo()
    if not torch.cuda.is_available():  # train() asks before it builds anything
        from helpers import train_in_process

        with pytest.raises(ValueError, match=r"trainer.accelerator=gpu \(trainer=gpu\): this process sees no CUDA"):
            train_in_process(tmp_path / "b", "experiment=quick", f"data.root={dataset}", "trainer=gpu", "logger=none")
        assert not (tmp_path / "b" / "checkpoints").exists()


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_training_and_ray_print_no_known_third_party_noise(dataset, tmp_path, capfd):
    from spread.runtime.ray import RaySettings, ray_session

    proc = run_quietly("spread-train", "experiment=quick", f"data.root={dataset}", f"out_dir={tmp_path / 'run'}",
                       "trainer.max_time=null", "trainer.max_steps=2", "logger=wandb", *SMALL_MODEL, *(o for o in FAST_TRAIN if not o.startswith("logger=")))
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out[-3000:]
    for noise in ("💡 Tip", "anonymous setting", "log_every_n_steps", "LeafSpec"):
        assert noise not in out, noise
    with ray_session(RaySettings(num_cpus=1)):
        pass
    captured = capfd.readouterr()
    assert "Token authentication" not in captured.out + captured.err


def test_every_reader_refuses_a_device_by_name(tmp_path):
    from spread.data.stats import StatsError, load_stats
    from spread.safe_load import UnsafeFileError, load_checkpoint, load_npz

    for name in ("stats.json", "boxes.npz", "last.ckpt"):
        (tmp_path / name).symlink_to("/dev/zero")
    with within(5):
        with pytest.raises(StatsError, match=r"stats.json: not a regular file \(a character device\)"):
            load_stats(tmp_path / "stats.json")
        with pytest.raises(UnsafeFileError, match=r"boxes.npz: not a regular file"):
            load_npz(tmp_path / "boxes.npz")
        with pytest.raises(UnsafeFileError, match=r"last.ckpt: not a regular file"):
            load_checkpoint(tmp_path / "last.ckpt")


def test_generate_ablate_and_compare_refuse_a_folder_another_run_is_writing(tmp_path):
    """spread-generate, spread-ablate and spread-compare hold their out_dir's run lock as the other commands do:
    while another run holds it, they stop at once naming the holder, before writing anything."""
    from spread.configs import compose
    from spread.commands.ablate import ablate
    from spread.commands.generate import generate
    from spread.commands.compare import compare
    from spread.io import RunFolderBusy, run_lock

    for name, run, overrides in (("generate", generate, ["rooms=2"]),
                                 ("ablate", ablate, ["+preset=quick", "logger=none"]),
                                 ("compare", compare, ["+table1=quick", "logger=none"])):
        folder = tmp_path / name
        with run_lock(folder, "a test holding the folder"):
            with pytest.raises(RunFolderBusy, match="a test holding the folder"):
                run(compose(name, [f"out_dir={folder}", *overrides]))
        assert sorted(p.name for p in folder.iterdir()) == [".spread.lock"]  # nothing else was written


def test_a_run_lock_whose_file_was_removed_while_it_was_taken_locks_the_file_now_there(tmp_path, monkeypatch):
    """A refused command removes the lock file it made (cli.errors.FolderLeftEmpty); a run that opened that file
    just before and locks it after must not hold a lock on a file no longer there (two runs, two locks, one name)."""
    import fcntl

    import spread.io as io

    real_flock, calls = fcntl.flock, []

    def flock_then_removed(fd, op):  # the file is removed between this run's open and its flock
        real_flock(fd, op)
        if not calls:
            calls.append(fd)
            (tmp_path / io.LOCK_FILE).unlink()

    monkeypatch.setattr(fcntl, "flock", flock_then_removed)
    with io.run_lock(tmp_path, "spread-evaluate") as path:
        assert path.read_text().startswith("spread-evaluate (pid") and len(calls) == 1
        with pytest.raises(io.RunFolderBusy, match="in use by a running spread-evaluate"):
            with io.run_lock(tmp_path, "spread-sample"):
                pass


def test_a_refused_commands_cleanup_racing_another_run_leaves_that_run_its_folder_and_its_lock(tmp_path, monkeypatch):
    """Races a review found in the cleanup of a refused command (cli.errors.FolderLeftEmpty) against a run starting
    on the same new folder: the refused run removed the folder between the other's open and flock (the other then
    failed with FileNotFoundError), and a refused run that had opened the old lock file unlinked the new one a
    running run held (a third run then took the folder too)."""
    import fcntl
    import os
    import threading
    import time

    import spread.io as io
    from spread.cli.errors import FolderLeftEmpty

    folder = tmp_path / "run"
    refused = FolderLeftEmpty.of([f"out_dir={folder}"])
    with io.run_lock(folder, "spread-train"):  # the refused run held it, then was refused
        pass
    real_flock, cleaned = fcntl.flock, []

    def cleanup_between_open_and_flock(fd, op):
        if not cleaned:
            cleaned.append(1)
            refused.remove()  # lock and folder gone
            assert not folder.exists()
        return real_flock(fd, op)

    monkeypatch.setattr(fcntl, "flock", cleanup_between_open_and_flock)
    with io.run_lock(folder, "spread-sample") as path:  # made the folder and its lock again, and holds it
        assert cleaned and path.read_text().startswith("spread-sample (pid")
        monkeypatch.setattr(fcntl, "flock", real_flock)
        assert not io.remove_held_lock(path) and path.exists()  # held: not removed
    # a remover that opened the old file just before it was replaced: it must not unlink the new one
    old_ino = path.stat().st_ino
    real_open, swapped = os.open, []

    def replaced_after_open(file, flags, *args):
        fd = real_open(file, flags, *args)
        if str(file) == str(path) and not swapped:
            swapped.append(1)
            path.unlink()
            path.write_text("")  # another run's new lock file
        return fd

    monkeypatch.setattr(os, "open", replaced_after_open)
    assert not io.remove_held_lock(path)
    monkeypatch.setattr(os, "open", real_open)
    assert swapped and path.exists() and path.stat().st_ino != old_ino
    # a run that starts while a refused run holds its lock for the moment it takes to remove it is not refused
    got = []
    holder = real_open(path, os.O_RDWR)
    real_flock(holder, fcntl.LOCK_EX)

    def start():
        with io.run_lock(folder, "spread-evaluate"):
            got.append(True)

    thread = threading.Thread(target=start)
    thread.start()
    time.sleep(0.08)
    path.unlink()  # the refused run removes its lock, then lets go
    os.close(holder)
    thread.join(10)
    assert got == [True]
