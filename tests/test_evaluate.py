"""spread-evaluate end to end on a small generated split: ground-truth values, bad files, resume, a worker
killed mid-run, a two-node Ray cluster, and the driver-side pieces (resume compaction, merge_state).

Stability runs are reduced (``protocol.stability_runs=2``) for speed; every other protocol value is the
default. One module-scoped run of the console script is the reference the other runs are compared with.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from spread.io import append_jsonl, read_jsonl
from spread.scene import Scene, list_scene_files, read_scene, write_scene

from helpers import asset_library

ROOMS = 4
FAST = ["protocol.stability_runs=2", "ray.num_cpus=2", "progress=false", "renders=3"]
BAD = {"bad_missing_asset": "unknown asset 'no_such_asset_00'", "bad_nan": "non-finite",
       "bad_empty": "no objects"}
METRIC_KEYS = ("col_mesh", "grecall", "asd", "stability", "still_fraction", "displacement_ok_fraction",
               "rotation_ok_fraction", "fid", "kid", "fid_status", "fid_feature_model", "n_scenes", "n_objects",
               "n_failed")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A dataset folder whose test split holds ROOMS generated rooms (val/train empty)."""
    from spread.procgen.dataset import AssetSource, DatasetConfig, generate_dataset
    from spread.procgen.room_types import RoomConfig

    lib = tmp_path_factory.mktemp("evlib") / "assets"
    asset_library(lib)
    out = tmp_path_factory.mktemp("evdata") / "data"
    generate_dataset(out, DatasetConfig(rooms=ROOMS, seed=5, processes=1, renders=0, val_fraction=0.0,
                                        test_fraction=1.0, assets=AssetSource(copy_from=str(lib)),
                                        room=RoomConfig(max_objects=24)), progress=False)
    assert len(list_scene_files(out / "test")) == ROOMS
    return out


def write_bad_scenes(folder: Path, good: Scene) -> None:
    """Three files the evaluation must report and skip: a missing asset, a NaN pose, no objects."""
    missing = good.with_poses(good.translation, good.rotation, scene_id="bad_missing_asset")
    missing.asset_id = np.array(["no_such_asset_00", *missing.asset_id[1:].tolist()])
    write_scene(missing, folder / "bad_missing_asset.npz")
    nan = good.with_poses(good.translation, good.rotation, scene_id="bad_nan")
    nan.translation[1, 0] = np.nan
    write_scene(nan, folder / "bad_nan.npz", validate=False)
    empty = Scene("bad_empty", np.zeros(0, str), np.zeros(0, str), np.zeros((0, 3)), np.zeros((0, 3, 3)),
                  np.zeros((0, 0)), np.zeros((0, 0)))
    write_scene(empty, folder / "bad_empty.npz", validate=False)


@pytest.fixture(scope="module")
def scenes_dir(dataset, tmp_path_factory):
    folder = tmp_path_factory.mktemp("evscenes") / "scenes"
    shutil.copytree(dataset / "test", folder)
    write_bad_scenes(folder, read_scene(list_scene_files(folder)[0]))
    return folder


def args(scenes: Path, dataset: Path, out: Path, *extra: str) -> list[str]:
    return [f"scenes={scenes}", f"reference={dataset}", f"out_dir={out}", *FAST, *extra]


@pytest.fixture(scope="module")
def cli_run(dataset, scenes_dir, tmp_path_factory):
    """One run of the console script (wandb through the real code path, WANDB_MODE=disabled)."""
    out = tmp_path_factory.mktemp("evout") / "run"
    script = Path(sys.executable).parent / "spread-evaluate"
    env = {**os.environ, "WANDB_MODE": "disabled"}
    proc = subprocess.run([str(script), *args(scenes_dir, dataset, out, "logger=wandb")], env=env,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out, json.loads((out / "metrics.json").read_text()), proc.stdout


def run_in_process(*overrides: str):
    """Compose conf/evaluate.yaml with ``overrides`` and call the Hydra entry (no subprocess)."""
    from spread.cli.evaluate import main
    from spread.configs import compose

    main(compose("evaluate", list(overrides)))


def comparable(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if k not in ("run", "versions", "scenes")}


def assert_each_scene_once(out: Path, scenes: Path) -> list[dict]:
    lines = read_jsonl(out / "per_scene.jsonl")
    ids = [r["scene_id"] for r in lines]
    assert sorted(ids) == sorted(p.stem for p in list_scene_files(scenes))
    return lines


# ---- the console script on ground truth + bad files ----------------------------------------------

def test_files_and_keys(cli_run):
    out, metrics, stdout = cli_run
    for name in ("metrics.json", "per_scene.jsonl", "protocol.json", ".hydra/config.yaml"):
        assert (out / name).exists(), name
    assert len(list((out / "renders").glob("*.png"))) == 3
    for key in METRIC_KEYS:
        assert key in metrics, key
    protocol = metrics["protocol"]
    assert protocol["stability_runs"] == 2 and protocol["stability_steps"] == 100
    assert protocol["collision_threshold"] == 0.01 and protocol["stability_jitter"] == 5e-4
    assert protocol["stability_substeps"] == 4 and protocol["fid_render"]["image_size"] == 256
    assert {"spread", "torch", "pybullet", "trimesh", "ray"} <= set(metrics["versions"])
    assert "Col_mesh" in stdout and "95 % interval" in stdout and "[0.000, 0.000]" in stdout  # Col_mesh's
    assert "interval: the 95 % percentile bootstrap interval over scenes (1,000 resamples, seed 0)" in stdout


def test_ground_truth_split_scores_as_ground_truth(cli_run):
    metrics = cli_run[1]
    assert metrics["n_scenes"] == ROOMS + 3 and metrics["n_evaluated"] == ROOMS
    assert metrics["col_mesh"] == 0.0
    assert metrics["grecall"] == 1.0
    assert metrics["asd"] < 1e-3  # metres
    assert metrics["stability"] >= 0.98
    assert metrics["n_objects"] > 2 * ROOMS
    # the bootstrap over scenes: ground truth never collides and keeps every relation, so those intervals have
    # zero width; the seed is the protocol's and only the evaluated scenes are resampled
    assert metrics["col_mesh_lo"] == metrics["col_mesh_hi"] == 0.0
    assert metrics["grecall_lo"] == metrics["grecall_hi"] == 1.0
    assert metrics["asd_lo"] <= metrics["asd"] <= metrics["asd_hi"]
    assert {k: v for k, v in metrics["bootstrap"].items() if k != "measured"} == {
        "method": "percentile", "unit": "scene", "resamples": 1000, "level": 0.95,
        "seed": metrics["protocol"]["seed"], "n_scenes": ROOMS}
    assert metrics["bootstrap"]["measured"]["grecall"] == ROOMS


def test_fid_and_kid_come_offline_from_the_shipped_inception_weights(cli_run):
    metrics = cli_run[1]  # the evaluated good scenes are the reference split itself
    assert metrics["fid_status"].startswith("ok: inception_v3") and metrics["fid_feature_model"] == "inception_v3"
    assert metrics["fid_num_generated"] == metrics["fid_num_reference"] == ROOMS
    assert metrics["fid"] == 0.0
    assert np.isfinite(metrics["kid"]) and metrics["kid_subset_size"] == ROOMS


@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_clip_fid_without_local_clip_weights_is_null_with_the_reason(dataset, tmp_path):
    out = tmp_path / "run"
    run_in_process(*args(dataset / "test", dataset, out, "logger=none", "fid=clip", "metrics=[grecall]", "renders=0"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["fid"] is None and metrics["kid"] is None and metrics["fid_feature_model"] == "clip_vit_b_32"
    assert metrics["fid_status"].startswith("unavailable") and "clip" in metrics["fid_status"].lower()


@pytest.mark.slow  # make test-slow (~15-30 s): MuJoCo's sleep is checked in test_mujoco, the Ray fan-out by cli_run
def test_ground_truth_is_stable_in_sleeping_mujoco_through_the_ray_fanout(dataset, tmp_path):
    out = tmp_path / "run"
    run_in_process(*args(dataset / "test", dataset, out, "logger=none", "fid.enabled=false", "renders=0",
                         "protocol.physics=mujoco", "protocol.physics_sleep=true"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["protocol"]["physics"] == "mujoco" and metrics["protocol"]["physics_params"]["sleep"] is True
    assert metrics["n_evaluated"] == ROOMS and metrics["stability"] >= 0.98 and metrics["still_fraction"] >= 0.98


def test_bad_files_are_counted_and_listed_with_their_errors(cli_run):
    out, metrics, _ = cli_run
    assert metrics["n_failed"] == 3
    failed = {f["scene_id"]: f["error"] for f in metrics["failed"]}
    lines = {r["scene_id"]: r for r in read_jsonl(out / "per_scene.jsonl")}
    for name, text in BAD.items():
        assert text in failed[name], failed[name]
        assert text in lines[name]["error"]
    good = [r for r in lines.values() if not r["error"]]
    assert len(good) == ROOMS and all(r["state"] and r["seconds"]["stability"] > 0 for r in good)


# ---- resume, worker death, cluster ---------------------------------------------------------------

@pytest.mark.slow  # long (≈ 30 s on 2 cores): make test-slow runs it; the fast guard is
# test_load_finished_drops_duplicates_and_a_torn_line
def test_resume_after_a_torn_line_counts_every_scene_once(cli_run, dataset, scenes_dir, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(cli_run[0], out)
    lines = (out / "per_scene.jsonl").read_text().splitlines(keepends=True)
    (out / "per_scene.jsonl").write_text("".join(lines[:2]) + lines[2][:57])  # a killed writer's torn line
    run_in_process(*args(scenes_dir, dataset, out, "logger=none"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["run"]["resumed"] == 2 and metrics["run"]["evaluated_this_run"] == ROOMS + 1
    assert_each_scene_once(out, scenes_dir)
    assert comparable(metrics) == comparable(cli_run[1])


def test_a_rerun_after_a_scene_was_removed_drops_its_render_and_records_the_scenes_folder_absolute(
        cli_run, dataset, scenes_dir, tmp_path, monkeypatch):
    """A review found the removed scene's top-down left in ``renders/`` (the report showed it as this run's), and
    ``metrics.json``'s ``scenes`` as typed (relative), which a report run from another folder could not find."""
    out = tmp_path / "run"
    shutil.copytree(cli_run[0], out)
    shutil.copytree(scenes_dir, tmp_path / "scenes")
    before = sorted(p.stem for p in (out / "renders").glob("*.png"))
    assert len(before) == 3
    (tmp_path / "scenes" / f"{before[0]}.npz").unlink()
    monkeypatch.chdir(tmp_path)
    run_in_process(*args(Path("scenes"), dataset, out, "logger=none"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["scenes"] == str(tmp_path / "scenes")
    after = sorted(p.stem for p in (out / "renders").glob("*.png"))
    assert before[0] not in after and len(after) == 3 and set(after) <= set(metrics["evaluated_scenes"])


def test_scenes_that_are_the_reference_splits_own_files_get_a_warning_with_their_fid(cli_run, dataset, tmp_path):
    """FID 0.00 of a folder against itself was reported as an ordinary value (status "ok"). A copy of the split is
    found by content (the split itself too: the same files); other scenes (``cli_run``'s: the split and bad files)
    get none."""
    shutil.copytree(dataset / "test", tmp_path / "copy")
    run_in_process(f"scenes={tmp_path / 'copy'}", f"reference={dataset}", f"out_dir={tmp_path / 'out'}",
                   "logger=none", "metrics=[grecall]", "progress=false", "renders=0", "ray.num_cpus=1")
    status = json.loads((tmp_path / "out" / "metrics.json").read_text())["fid_status"]
    assert status.startswith("ok: ") and "; warning: scenes= holds the reference split's own files" in status, status
    assert cli_run[1]["fid_status"].startswith("ok: ") and "warning" not in cli_run[1]["fid_status"]


def test_an_evaluation_in_the_sampling_runs_own_folder_leaves_its_renders_as_they_are(cli_run, dataset, scenes_dir,
                                                                                      tmp_path):
    """``spread-sample evaluate=true`` / ``spread-evaluate out_dir=<run>``: the folder's ``renders/`` are the sampling
    run's (ground truth | generated, named by scene as the evaluation's top-downs are): an evaluation neither writes
    over them nor deletes them when it is redone with another protocol (it did both)."""
    from spread.evaluation import EvalProtocol, FIDConfig
    from spread.evaluation.run import check_protocol

    run = tmp_path / "run"
    shutil.copytree(scenes_dir, run / "scenes")
    for name in ("per_scene.jsonl", "protocol.json", "metrics.json"):
        shutil.copy(cli_run[0] / name, run / name)
    ids = [p.stem for p in list_scene_files(scenes_dir)][:2]
    for sid in ids:
        (run / "renders").mkdir(exist_ok=True)
        (run / "renders" / f"{sid}.png").write_bytes(b"ground truth | generated")
        (run / "renders" / f"{sid}_3d.png").write_bytes(b"3d card")
    run_in_process(*args(run / "scenes", dataset, run, "logger=none"))
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["run"]["evaluated_this_run"] == 0  # resumed: every scene's line was there
    assert sorted(p.name for p in (run / "renders").iterdir()) == sorted(f"{s}{x}.png" for s in ids for x in ("", "_3d"))
    assert {(run / "renders" / f"{s}.png").read_bytes() for s in ids} == {b"ground truth | generated"}
    other = EvalProtocol(stability_runs=1)
    assert check_protocol(run, other, FIDConfig(), True, str(dataset / "assets"), own_renders=False)
    assert not (run / "metrics.json").exists() and len(list((run / "renders").glob("*.png"))) == 4
    shutil.copy(cli_run[0] / "per_scene.jsonl", run / "per_scene.jsonl")  # lines of the first protocol again
    assert check_protocol(run, EvalProtocol(), FIDConfig(), True, str(dataset / "assets"))  # its own folder's: cleared
    # … its own pictures (<scene_id>.png of the scenes its lines measured), never another picture of the folder
    assert sorted(p.name for p in (run / "renders").glob("*.png")) == sorted(f"{s}_3d.png" for s in ids)


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_a_relaunch_with_another_protocol_redoes_every_scene_and_says_why(cli_run, dataset, scenes_dir, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(cli_run[0], out)
    run_in_process(*args(scenes_dir, dataset, out, "logger=none", "protocol.stability_steps=50"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["redone_because"] == "changed: protocol.stability_steps"
    assert metrics["protocol"]["stability_steps"] == 50
    assert metrics["run"]["resumed"] == 0 and metrics["run"]["evaluated_this_run"] == len(list_scene_files(scenes_dir))
    assert_each_scene_once(out, scenes_dir)
    run_in_process(*args(scenes_dir, dataset, out, "logger=none", "protocol.stability_steps=50"))  # identical: resumed
    again = json.loads((out / "metrics.json").read_text())
    assert again["redone_because"] is None and again["run"]["evaluated_this_run"] == 0


def test_scenes_over_the_object_limit_are_left_out_by_name_and_their_lines_kept_for_a_relaunch_without_it(
        cli_run, dataset, scenes_dir, tmp_path):
    """A 130-object room took 88 s a Stability run: ``max_objects`` leaves larger scenes out before any work, named
    with their counts in ``metrics.json`` and in its identity (the numbers average over fewer scenes), and the
    aggregates are those of the other scenes' lines, whose lines stay for a relaunch without the limit; at the default
    (twice the reference's largest) the dataset's own rooms are all in."""
    assert cli_run[1]["scenes_over_limit"] == [] and "scenes_over_limit" not in cli_run[1]["evaluated_with"]
    sizes = {p.stem: read_scene(p).num_objects for p in list_scene_files(dataset / "test")}
    limit = sorted(sizes.values())[len(sizes) // 2]
    big = {k: n for k, n in sizes.items() if n > limit}
    assert big and len(big) < len(sizes)
    out = tmp_path / "run"
    shutil.copytree(cli_run[0], out)
    run_in_process(*args(scenes_dir, dataset, out, "logger=none", f"max_objects={limit}"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert {r["scene_id"]: r["objects"] for r in metrics["scenes_over_limit"]} == big
    assert metrics["evaluated_with"]["scenes_over_limit"] == sorted(big)
    assert not set(big) & set(metrics["evaluated_scenes"])
    assert metrics["n_scenes"] == cli_run[1]["n_scenes"] - len(big) and metrics["run"]["evaluated_this_run"] == 0
    from spread.evaluation.aggregate import summary_values
    from spread.evaluation.protocol import EvalProtocol

    kept = [r for r in read_jsonl(out / "per_scene.jsonl") if r["scene_id"] not in big]
    expected = summary_values(kept, EvalProtocol(stability_runs=2))
    assert {k: metrics[k] for k in ("col_mesh", "grecall", "asd", "stability")} == \
        {k: expected[k] for k in ("col_mesh", "grecall", "asd", "stability")}
    assert metrics["n_objects"] == cli_run[1]["n_objects"] - sum(big.values())
    # their lines stay, so a relaunch without the limit resumes them (the first run's metrics, as cli_run's folder)
    assert {r["scene_id"] for r in read_jsonl(out / "per_scene.jsonl")} >= set(big)


def test_an_evaluation_whose_every_scene_is_over_the_object_limit_is_refused_in_one_line(dataset, tmp_path):
    from helpers import user_error

    largest = max(read_scene(p).num_objects for p in list_scene_files(dataset / "test"))
    line, _ = user_error("spread-evaluate", *args(dataset / "test", dataset, tmp_path / "run", "logger=none",
                                                  "max_objects=1"))
    assert line.startswith(f"spread-evaluate: scenes={dataset / 'test'}: every scene is over the object limit 1 (the "
                           f"largest holds {largest} objects; set max_objects=<n> to raise it, 0: no limit)"), line
    assert not (tmp_path / "run").exists()


def test_the_object_count_is_read_from_a_scene_file_alone_and_a_file_that_is_no_scene_has_none(dataset, tmp_path):
    from spread.data.limit import object_count, scenes_over

    files = list_scene_files(dataset / "test")
    assert [object_count(f) for f in files] == [read_scene(f).num_objects for f in files]
    (tmp_path / "text.npz").write_text("not a zip")
    np.savez(tmp_path / "nokey.npz", translation=np.zeros((3, 3)))
    import zipfile

    with zipfile.ZipFile(tmp_path / "raw.npz", "w") as z:  # members that are not .npy arrays: read as bytes
        z.writestr("asset_id", b"abc")
    os.mkfifo(tmp_path / "fifo.npz")
    assert [object_count(tmp_path / n) for n in ("text.npz", "nokey.npz", "raw.npz", "fifo.npz", "gone.npz")] == \
        [None] * 5
    counts = {f: read_scene(f).num_objects for f in files}
    assert scenes_over(files, None) == {} and scenes_over(files, min(counts.values()) - 1) == counts
    assert scenes_over([*files, tmp_path / "text.npz"], 0) == counts
    damaged = read_scene(files[0])  # 50 asset ids beside the poses of fewer: its reader refuses it, not the limit
    np.savez(tmp_path / "damaged.npz", **{"scene_id": np.array("damaged"), "asset_id": np.array(["a"] * 50),
                                          "category": damaged.category, "translation": damaged.translation,
                                          "rotation": damaged.rotation, "spatial": damaged.spatial,
                                          "physical": damaged.physical})
    assert object_count(tmp_path / "damaged.npz") == 50 and scenes_over([tmp_path / "damaged.npz"], 3) == {}


@pytest.mark.slow  # make test-slow; make test keeps test_a_scene_that_always_kills_its_worker_is_reported_alone
@pytest.mark.parametrize("max_retries", [3, 0])
def test_a_worker_killed_mid_run_loses_no_scene(cli_run, dataset, scenes_dir, tmp_path, monkeypatch, max_retries):
    """A worker exits after its first scene: Ray re-runs the task (max_retries=3), or, with no retries left,
    the driver splits the failed chunk into one task per scene (max_retries=0)."""
    from spread.evaluation.work import FAULT_MARKER_ENV

    marker = tmp_path / "killed"
    monkeypatch.setenv(FAULT_MARKER_ENV, str(marker))  # inherited by the Ray workers started below
    out = tmp_path / "run"
    run_in_process(*args(scenes_dir, dataset, out, "logger=none", "chunk_size=3", f"ray.max_retries={max_retries}"))
    assert marker.exists(), "no worker was killed"
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["run"]["split_chunks"] == (1 if max_retries == 0 else 0)
    assert_each_scene_once(out, scenes_dir)
    assert comparable(metrics) == comparable(cli_run[1])


EXTRACTOR_MODULE = '''
import numpy as np


class ColourStats:
    """Per-channel mean and spread of an image: 6 features (a stand-in backbone for the test)."""

    feature_dim = 6

    def __call__(self, images):
        x = np.asarray(images, np.float64).reshape(len(images), -1, 3)
        return np.concatenate([x.mean(1), x.std(1)], 1)


def factory():
    return ColourStats()
'''


def test_fid_with_an_injected_backbone_is_zero_for_the_reference_itself(dataset, tmp_path, monkeypatch):
    (tmp_path / "evfid.py").write_text(EXTRACTOR_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    out = tmp_path / "run"
    run_in_process(*args(dataset / "test", dataset, out, "logger=none", "chunk_size=2",
                         "fid.extractor=evfid:factory", "fid.feature_model=colour_stats", "metrics=[grecall]"))
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["fid_status"].startswith("ok") and metrics["fid_feature_model"] == "colour_stats"
    assert metrics["fid_num_generated"] == metrics["fid_num_reference"] == ROOMS
    assert metrics["fid"] == 0.0  # the same scenes, so the same features: exactly 0, never a rounding residue
    lines = read_jsonl(out / "per_scene.jsonl")
    assert all(len(r["fid_features"]) == 6 for r in lines)


@pytest.mark.slow  # a two-node cluster (~23 s); make test has one: test_scaleout's sampling on two nodes
def test_two_node_cluster_runs_chunks_on_both_nodes(cli_run, dataset, tmp_path):
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    try:
        cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        out = tmp_path / "run"
        run_in_process(*args(dataset / "test", dataset, out, "logger=none", "chunk_size=1",
                             f"ray.address={cluster.address}"))
    finally:
        ray.shutdown()
        cluster.shutdown()
    lines = assert_each_scene_once(out, dataset / "test")
    assert len({r["node_id"] for r in lines}) == 2
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["run"]["ray"]["nodes"] == 2
    expected = comparable(cli_run[1])
    for key in ("col_mesh", "grecall", "asd", "stability", "still_fraction", "n_objects"):
        assert metrics[key] == expected[key], key


# ---- driver-side pieces, no Ray ------------------------------------------------------------------

def test_load_finished_drops_duplicates_and_a_torn_line(tmp_path):
    from spread.evaluation.resume import load_finished

    path = tmp_path / "per_scene.jsonl"
    for sid in ("a", "b", "a"):
        append_jsonl(path, {"scene_id": sid, "error": None})
    append_jsonl(path, {"scene_id": "c", "error": "ValueError: bad"})
    with open(path, "a") as fh:
        fh.write('{"scene_id": "d", "err')
    assert list(load_finished(path)[0]) == ["a", "b", "c"]
    append_jsonl(path, {"scene_id": "e", "error": None})  # lands on its own line after compaction
    assert [r["scene_id"] for r in read_jsonl(path)] == ["a", "b", "c", "e"]
    assert list(load_finished(path, retry_failed=True)[0]) == ["a", "b", "e"]


def test_records_merge_to_the_metrics_of_all_scenes_at_once(cli_run, dataset):
    """merge_state over per-scene states (the driver's path) equals one metric updated with every scene."""
    from spread.assets import AssetLibrary
    from spread.evaluation.aggregate import merge_records
    from spread.evaluation.protocol import EvalProtocol

    protocol = EvalProtocol(stability_runs=2)
    records = [r for r in read_jsonl(cli_run[0] / "per_scene.jsonl") if not r["error"]]
    merged = merge_records(records, protocol)
    library = AssetLibrary.load(dataset / "assets")
    scenes = [read_scene(p, assets=library) for p in list_scene_files(dataset / "test")]
    for name in ("col_mesh", "grecall", "asd"):
        whole = protocol.build_metrics()[name]
        whole.update(scenes, library)
        assert float(merged[name].compute()) == pytest.approx(float(whole.compute()), abs=1e-12), name
    assert float(merged["stability"].compute()["stability"]) == cli_run[1]["stability"]


def crash_on_boom(paths, tag):
    """A stand-in evaluation task: kills its worker on the scene named "boom", else one record per path."""
    if "boom" in paths:
        os._exit(1)
    return [{"scene_id": p, "error": None, "tag": tag} for p in paths]


def test_a_scene_that_always_kills_its_worker_is_reported_alone(monkeypatch):
    from spread.evaluation.fanout import fan_out
    from spread.evaluation.work import failure_record
    from spread.runtime.ray import RaySettings, ray_session

    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(Path(__file__).parent), os.environ.get("PYTHONPATH", "")]))
    settings = RaySettings(num_cpus=1, max_retries=1)
    records = []
    with ray_session(settings):
        stats = fan_out(["a", "boom", "c", "d"], 3, settings, crash_on_boom, ("x",), records.append, failure_record)
    by_id = {r["scene_id"]: r for r in records}
    assert sorted(by_id) == ["a", "boom", "c", "d"] and len(records) == 4
    assert "worker failed" in by_id["boom"]["error"]
    assert all(by_id[k]["error"] is None for k in "acd")
    assert stats.split_chunks == 1 and stats.tasks == 2 + 3


def test_import_pulls_no_heavy_modules():
    """Nor torchmetrics (every metric module imports it, ~2.5 s): the schemas know the default metrics by name, so
    a console script that refuses its input, or prints --help, answers in about 2 s instead of 6."""
    code = ("import sys, spread.evaluation, spread.cli.evaluate, spread.cli.sample, spread.cli.sweep; "
            "from spread.configs import compose; compose('evaluate', ['scenes=/s', 'reference=/r', 'out_dir=/o']); "
            "compose('sample', ['ckpt=/c', 'data.root=/d', 'out_dir=/o']); "
            "print([m for m in ('ray', 'wandb', 'pybullet', 'cleanfid', 'torchmetrics') if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


def test_the_default_metrics_are_known_by_name_and_are_the_registered_defaults():
    from spread.evaluation.protocol import EvalProtocol
    from spread.metrics.registry import DEFAULT_METRICS, METRICS, MetricSpec, check_spec
    from spread.registry import RegistryError

    assert [name for name, spec in METRICS.items() if spec.default] == list(DEFAULT_METRICS)
    assert METRICS.names()[:4] == list(DEFAULT_METRICS)  # the order a protocol's set is written in
    assert EvalProtocol(metrics=["stability", "col_mesh"]).metrics == ["col_mesh", "stability"]
    assert EvalProtocol(metrics=["oob", "grecall"]).metrics == ["grecall", "oob"]  # through the registry
    with pytest.raises(RegistryError, match="named twice"):
        EvalProtocol(metrics=["asd", "asd"])
    with pytest.raises(RegistryError, match=r"metric 'mine' refused: default=True.*protocol.metrics=\[col_mesh"):
        check_spec("mine", MetricSpec("mine", METRICS.get("asd").metric, default=True), {})
