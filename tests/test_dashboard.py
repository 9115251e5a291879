"""``logger=mlflow``: a tiny train and a sample + evaluate in one SQLite store, read back through MLflow's
client and through ``spread-dashboard`` (the real ``mlflow server``) over HTTP on localhost."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

from helpers import FAST_SAMPLE, FAST_TRAIN, SCRIPTS, SMALL_MODEL, compose, free_port, make_dataset, train_in_process


#: A small library (a quarter less work than all categories): bedrooms, a few kitchens and studies.
CATEGORIES = ["bed", "nightstand", "wardrobe", "desk", "chair", "dining_table", "kitchen_counter", "shelf", "book", "mug"]


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """(folder, store URI, training run folder, sampling run folder): 6 training steps and one sampling run with
    ``evaluate=true``, both with ``logger=mlflow`` into ``<folder>/mlflow.db`` (the sampling run to wandb too,
    offline)."""
    from spread.commands.sample import sample

    root = tmp_path_factory.mktemp("mlstore")
    data = make_dataset(root / "ds", rooms=8, categories=CATEGORIES)
    uri = f"sqlite:///{root}/mlflow.db"
    logger = ["logger=mlflow", f"logger.tracking_uri={uri}"]
    train_dir = root / "train"
    train_in_process(train_dir, "experiment=quick", f"data.root={data}", "trainer.max_time=null",
                     "trainer.max_steps=6", "trainer.log_every_n_steps=1", "trainer.check_val_every_n_epoch=1",
                     "model.sample_every_n_epochs=1", "model.val_sampler=ddim-4", "model.val_sample_scenes=2",
                     "renders.every_n_epochs=2", "renders.sampler=ddim-4",
                     *SMALL_MODEL, *FAST_TRAIN, *logger)
    sample_dir = root / "sample"
    sample(compose("sample", f"ckpt={train_dir / 'checkpoints' / 'last.ckpt'}", f"data.root={data}",
                   f"out_dir={sample_dir}", *FAST_SAMPLE, "evaluate=true", "evaluation.protocol.stability_runs=1",
                   "evaluation.fid.enabled=false", "experiment_name=tiny_sample", *logger,
                   "logger.name=wandb+mlflow", "logger.mode=offline"))  # and a wandb offline run beside it
    return root, uri, train_dir, sample_dir


def runs_by_job(uri: str) -> dict:
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()])
    return {r.data.tags["spread.job_type"]: r for r in runs}


def test_train_and_sample_put_two_runs_with_curves_metrics_tags_and_lineage(store):
    from mlflow import MlflowClient

    root, uri, train_dir, sample_dir = store
    runs = runs_by_job(uri)
    assert set(runs) == {"train", "sample"}
    train, sampled = runs["train"], runs["sample"]
    client = MlflowClient(tracking_uri=uri)
    loss = client.get_metric_history(train.info.run_id, "train/loss")
    assert len(loss) >= 3 and len({m.step for m in loss}) == len(loss)  # a curve, one point per logged step
    assert {"val/loss", "val/grecall", "train/grad_norm"} <= set(train.data.metrics)
    # throughput beside the loss (issue 29): steps and scenes per second, the loader's share of the wall time
    speed = {k: train.data.metrics[k] for k in ("perf/steps_per_s", "perf/scenes_per_s", "perf/data_wait_share")}
    assert speed["perf/steps_per_s"] > 0 and speed["perf/scenes_per_s"] >= speed["perf/steps_per_s"]
    assert 0 <= speed["perf/data_wait_share"] < 1
    assert any(k.startswith("lr-") for k in train.data.metrics)
    assert train.data.params["model.variant"] == train.data.tags["spread.variant"]
    renders = [a.path for a in client.list_artifacts(train.info.run_id, "renders")]  # sampled every 2 epochs
    assert renders and renders[0].startswith("renders/epoch0001") and renders[0].endswith(".png")
    assert train.info.status == "FINISHED" and sampled.info.status == "FINISHED"
    # the sampling run: every metric of metrics.json with its interval, the per-room-type breakdown, artifacts
    metrics = json.loads((sample_dir / "metrics.json").read_text())
    assert sampled.data.metrics["grecall"] == pytest.approx(metrics["grecall"])
    assert sampled.data.metrics["grecall_lo"] <= sampled.data.metrics["grecall"] <= sampled.data.metrics["grecall_hi"]
    room = next(iter(metrics["per_room_type"]))
    assert sampled.data.metrics[f"room/{room}/grecall"] == pytest.approx(metrics["per_room_type"][room]["grecall"])
    assert sampled.data.tags["spread.training_run_id"] == train.info.run_id  # lineage
    assert sampled.data.tags["spread.sampler"] == "ddim-4" and sampled.data.tags["spread.guidance"] == "none"
    assert sampled.data.tags["spread.dataset_fingerprint"] == train.data.tags["spread.dataset_fingerprint"]
    assert sampled.data.params["experiment_name"] == "tiny_sample"
    artifacts = {a.path for a in client.list_artifacts(sampled.info.run_id)}
    assert {"metrics.json", "per_scene.jsonl", "renders"} <= artifacts
    assert client.get_experiment(sampled.info.experiment_id).name == "tiny_sample"
    assert (root / "mlartifacts").is_dir()  # artifacts beside the store


def test_the_sampling_run_on_wandb_has_a_name_per_room_type_metrics_and_lineage(store):
    from spread.reporting.runs import read_wandb_file

    root, uri, train_dir, sample_dir = store
    found = list((sample_dir / "wandb").glob("offline-run-*/*.wandb"))
    assert len(found) == 1
    run = read_wandb_file(found[0])
    metrics = json.loads((sample_dir / "metrics.json").read_text())
    room = next(iter(metrics["per_room_type"]))
    assert run["name"] == "sample" and run["summary"]["grecall"] == pytest.approx(metrics["grecall"])
    assert run["summary"][f"room/{room}/grecall"] == pytest.approx(metrics["per_room_type"][room]["grecall"])
    lineage = run["config"]["lineage"]
    assert lineage["spread.training_run_folder"] == str(train_dir.resolve())
    assert lineage["spread.training_run_id"] == runs_by_job(uri)["train"].info.run_id



def test_tracker_records_name_the_checkpoint_and_data_the_numbers_were_measured_with_as_the_folder_does(store):
    """A report of wandb runs (or of the MLflow store) gave runs of two checkpoints one identity: the config has
    the checkpoint's path, not its content; the trackers now carry ``metrics.json``'s record of it."""
    from spread.reporting.runs import read_run_folder, read_wandb_run
    from spread.results import load

    root, uri, train_dir, sample_dir = store
    folder = read_run_folder(sample_dir)
    (wandb_run,) = (sample_dir / "wandb").glob("offline-run-*")
    logged = read_wandb_run(wandb_run)
    assert "ckpt" in folder["settings"] and logged["settings"] == folder["settings"]
    assert logged["identity"] == folder["identity"]
    shutil.move(str(sample_dir / "metrics.json"), str(root / "metrics.json.aside"))  # the folder's record gone
    try:
        rows = load(str(root / "mlflow.db"))
    finally:
        shutil.move(str(root / "metrics.json.aside"), str(sample_dir / "metrics.json"))
    row = rows[rows["run_name"] == "sample"].iloc[0]
    assert row["identity"] == folder["identity"] and row["ckpt"] == folder["settings"]["ckpt"]


def get(url: str, data: dict | None = None):
    body = None if data is None else json.dumps(data).encode()
    request = urllib.request.Request(url, data=body, headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=10) as response:
        return response.status, response.read()


class Dashboard:
    """``spread-dashboard`` in its own process group on a free port; :meth:`stop` ends that group."""

    def __init__(self, uri: str):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc = subprocess.Popen([str(SCRIPTS / "spread-dashboard"), f"tracking_uri={uri}", f"port={self.port}"],
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                     start_new_session=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
        deadline = time.time() + 120
        while time.time() < deadline:
            assert self.proc.poll() is None, self.proc.stdout.read()[-3000:]
            try:
                if get(self.url + "/health")[0] == 200:
                    return
            except OSError:
                time.sleep(0.5)
        self.stop()
        raise AssertionError("spread-dashboard did not answer in 120 s")

    def commands(self) -> list[str]:
        """The command lines of the dashboard's processes (its process group: the MLflow server and its workers)."""
        lines = []
        for pid in filter(str.isdigit, os.listdir("/proc")):
            try:
                if os.getpgid(int(pid)) == self.proc.pid:
                    lines.append(Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode())
            except (OSError, ProcessLookupError):
                pass  # ended while we looked
        return lines

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()


@pytest.fixture(scope="module")
def dashboard(store):
    server = Dashboard(store[1])
    yield server
    server.stop()


def test_dashboard_serves_the_ui_and_lists_experiments_runs_and_metrics_over_rest(store, dashboard):
    status, page = get(dashboard.url + "/")
    assert status == 200 and b"<html" in page.lower()
    status, body = get(dashboard.url + "/api/2.0/mlflow/experiments/search", {"max_results": 100})
    names = {e["name"] for e in json.loads(body)["experiments"]}
    assert {"quick", "tiny_sample"} <= names
    ids = [e["experiment_id"] for e in json.loads(body)["experiments"]]
    status, body = get(dashboard.url + "/api/2.0/mlflow/runs/search", {"experiment_ids": ids})
    runs = json.loads(body)["runs"]
    assert len(runs) == 2
    metrics = {m["key"] for r in runs for m in r["data"].get("metrics", [])}
    assert {"grecall", "grecall_lo", "grecall_hi", "train/loss"} <= metrics
    # the MLflow server without its job runner (huey consumers for GenAI jobs): nothing the dashboard serves needs it
    commands = dashboard.commands()
    assert any("mlflow" in c for c in commands) and not any("huey" in c for c in commands), commands


def test_dashboard_refuses_unknown_arguments_by_name():
    proc = subprocess.run([str(SCRIPTS / "spread-dashboard"), "prot=5"], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "'prot=5'" in proc.stderr


# ---- spread-report's HTML page -------------------------------------------------------------------------------

def test_report_of_a_sampling_run_and_a_training_run_is_one_self_contained_html_page(store, tmp_path):
    from spread.reporting.report import run_report

    root, uri, train_dir, sample_dir = store
    result = run_report([str(sample_dir), str(train_dir)], tmp_path / "R")
    page = (tmp_path / "R" / "report.html").read_text()
    assert page.startswith("<!DOCTYPE html>") and "Training curves (1 runs)" in page
    assert "train/loss" in result.html["curves"] and any(k.startswith("lr-") for k in result.html["curves"])
    metrics = json.loads((sample_dir / "metrics.json").read_text())
    room = next(iter(metrics["per_room_type"]))
    assert result.html["room_rows"] == len(metrics["per_room_type"]) and f"<td>{room}</td>" in page
    from spread.reporting.tables import metric_columns

    METRICS = metric_columns()

    measured = [c.key for c in METRICS if metrics.get(c.key) is not None]  # one plot each (no weight varies)
    assert len(measured) >= 3 and result.html["metric_plots"] == len(measured) and result.html["renders"] == 1
    # self-contained: every image inline, nothing fetched from elsewhere
    assert page.count('src="data:image/png;base64,') >= 3 and "http" not in page.replace("https://", "")
    assert "<script" not in page
    md = (tmp_path / "R" / "report.md").read_text()
    assert "## Training runs (1)" in md and (tmp_path / "R" / "report_training.csv").exists()
    # the steps trained, as metrics.json and the console say them (the last logged step, 0-based, said 5 for 6)
    from spread.reporting.html_report import read_curves, steps_trained
    from spread.reporting.tables import read_csv

    assert read_csv(tmp_path / "R" / "report_training.csv")[0]["steps"] == 6
    assert steps_trained(tmp_path / "nowhere", read_curves(train_dir)) == 6  # no metrics.json: last logged + 1


@pytest.mark.slow  # the console script's start-up (Hydra, imports) is most of it; run_report is tested above
def test_spread_report_script_writes_the_html_page_of_a_sampling_run(store, tmp_path):
    from helpers import run_script

    run_script("spread-report", f"runs={store[3]}", f"out_dir={tmp_path / 'R'}")
    assert "<h2>Evaluated runs (1)</h2>" in (tmp_path / "R" / "report.html").read_text()


def test_report_of_training_runs_only_overlays_their_curves(store, tmp_path):
    from spread.reporting.html_report import read_curves
    from spread.reporting.report import run_report

    train_dir = store[2]
    curves = read_curves(train_dir)
    assert [s for s, _ in curves["train/loss"]] == sorted(s for s, _ in curves["train/loss"])
    assert len(curves["train/loss"]) >= 3
    result = run_report([str(train_dir)], tmp_path / "R")
    assert result.records == [] and result.html["training_runs"] == 1
    assert "Evaluated runs" not in (tmp_path / "R" / "report.html").read_text()


# ---- spread-view ---------------------------------------------------------------------------------------------

def test_viewer_collects_a_run_with_ground_truth_and_serves_scenes_coloured_by_category(store):
    from spread.render.palette import category_colour
    from spread.render.viewer import SceneViewer, collect, object_meshes
    from spread.scene import read_scene

    sample_dir = store[3]
    items, library_root = collect(sample_dir)
    assert len(items) == len(list((sample_dir / "scenes").glob("*.npz"))) >= 1
    assert all(item.ground_truth is not None and item.ground_truth.exists() for item in items)
    scene = read_scene(items[0].path)
    assert read_scene(items[0].ground_truth).scene_id == str(scene.extras["conditioned_on"])
    viewer = SceneViewer(items, library_root, port=free_port())
    try:
        status, page = get(f"http://127.0.0.1:{viewer.server.get_port()}/")
        assert status == 200 and b"<html" in page.lower()
        assert viewer.shown == ["/scene", "/ground_truth"]
        meshes = object_meshes(scene, viewer.library)
        assert [m[3] for m in meshes] == [category_colour(str(c)) for c in scene.category]
        assert all(c in viewer.legend.content for c in {str(c) for c in scene.category})
        viewer.physics.value = True  # the Stability simulation beside it
        assert viewer.shown == ["/scene", "/ground_truth", "/after"] and "moved" in viewer.info.content
    finally:
        viewer.server.stop()


def test_viewer_refuses_a_missing_path_by_name(tmp_path):
    from spread.render.viewer import collect

    with pytest.raises(FileNotFoundError, match="nothing_here"):
        collect(tmp_path / "nothing_here")


def test_viewer_names_an_asset_library_it_was_given_that_is_not_there(store, tmp_path):
    """It said "no asset library for <scenes> (looked beside it and in the dataset); give assets=DIR" to a user who
    had given ``assets=``."""
    from spread.render.viewer import collect

    root, _, _, sample_dir = store
    with pytest.raises(FileNotFoundError, match=rf"^spread-view: assets={tmp_path / 'none'}: no asset library there"):
        collect(sample_dir, assets=str(tmp_path / "none"))


# ---- the MLflow writer on its own ----------------------------------------------------------------------------

def test_a_run_opens_before_the_work_and_a_failure_marks_it_failed(tmp_path):
    from mlflow import MlflowClient

    from spread.tracking.mlflow_store import RUN_FILE, log_table, tracked
    from spread.tracking.loggers import LoggerConfig

    logger = LoggerConfig(name="wandb+mlflow", mode="disabled", tracking_uri=str(tmp_path / "store" / "m.db"))
    assert logger.wandb and logger.mlflow
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'store' / 'm.db'}")
    with pytest.raises(RuntimeError, match="boom"):
        with tracked(logger, "sample", tmp_path / "a", {"seed": 3, "guidance": {"collision": 0.01}}, "exp") as run:
            assert client.get_run(run.run_id).info.status == "RUNNING"  # open while the work runs
            raise RuntimeError("boom")
    failed = client.get_run(run.run_id)
    assert failed.info.status == "FAILED" and failed.data.params == {"seed": "3", "guidance.collision": "0.01"}
    assert json.loads((tmp_path / "a" / RUN_FILE).read_text())["run_id"] == run.run_id
    (tmp_path / "t.csv").write_text("variant,grecall\nbase,0.5\n")
    with tracked(logger, "ablation", tmp_path / "b", {}, "exp") as run:
        log_table(run, [{"variant": "base", "grecall": 0.5, "n": 3}, {"variant": "geometry", "grecall": None}],
                  "variant", [tmp_path / "t.csv"])
    done = client.get_run(run.run_id)
    assert done.info.status == "FINISHED" and done.data.metrics == {"base/grecall": 0.5, "base/n": 3.0}
    assert [a.path for a in client.list_artifacts(run.run_id, "table")] == ["table/t.csv"]


def test_a_point_a_relaunched_sweep_resumes_continues_its_run_under_the_relaunchs_parent(tmp_path):
    """A sweep killed while a point sampled: its relaunch resumes the point, whose run goes on (not a second run of
    the folder) and is folded under the relaunch's parent run, which has every point of the finished sweep."""
    from mlflow import MlflowClient

    from spread.tracking.continuation import Continuation
    from spread.tracking.loggers import LoggerConfig
    from spread.tracking.mlflow_store import tracked
    from spread.tracking.parent import parent_run

    logger = LoggerConfig(name="mlflow", tracking_uri=str(tmp_path / "m.db"))
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'm.db'}")
    point = tmp_path / "sweep" / "points" / "p1"
    runs = []
    for launch in range(2):
        again = Continuation(point, "sample", lambda: {"seed": 1}, resume=True)
        with pytest.raises(RuntimeError) if launch == 0 else contextlib.nullcontext():
            with parent_run(logger, "sweep", "s", tmp_path / "sweep", "s") as parent:
                with tracked(logger, "sample", point, {"seed": 1}, "s", continuation=again) as run:
                    again.record(run)
                    runs.append((parent.run.run_id, run.run_id))
                    if launch == 0:
                        raise RuntimeError("the driver was killed")
    (first_parent, first_run), (second_parent, second_run) = runs
    assert second_run == first_run and second_parent != first_parent
    done = client.get_run(first_run)
    assert done.info.status == "FINISHED" and done.data.tags["mlflow.parentRunId"] == second_parent
    assert done.data.tags["spread.launches"] == "2"


def test_logger_names_are_checked_and_combined():
    from spread.tracking.loggers import LoggerConfig

    assert LoggerConfig(name="mlflow").names == ("mlflow",) and not LoggerConfig(name="mlflow").wandb
    with pytest.raises(ValueError, match="'wandb\\+tensorboard'"):
        LoggerConfig(name="wandb+tensorboard")


def test_the_default_store_is_the_runs_folders_sqlite_file_for_every_command(tmp_path):
    from spread.tracking.mlflow_store import resolve_tracking_uri

    for command in ("train", "sample", "evaluate", "ablate", "compare"):
        cfg = compose(command, "logger=mlflow", f"paths.runs_dir={tmp_path / 'runs'}")
        assert cfg.logger.name == "mlflow" and cfg.logger.tracking_uri == f"sqlite:///{tmp_path / 'runs'}/mlflow.db"
    assert resolve_tracking_uri(str(tmp_path / "a" / "m.db")) == f"sqlite:///{tmp_path / 'a' / 'm.db'}"
    assert (tmp_path / "a").is_dir() and resolve_tracking_uri("http://host:5000") == "http://host:5000"


def test_report_takes_the_training_runs_inside_a_folder_beside_its_evaluated_runs(store, tmp_path):
    """An ablation's or comparison's folder holds both: its evaluated runs make the table, its training runs
    the curves."""
    from spread.reporting.html_report import training_folders

    root, _, train_dir, sample_dir = store
    training, rest = training_folders([str(root)])
    assert training == [train_dir] and rest == [str(root)]
    assert training_folders([str(train_dir), str(sample_dir)]) == ([train_dir], [str(sample_dir)])
    # a training run named twice, or under another spelling of its path, once (its row took another run's steps)
    twice = [str(train_dir), str(sample_dir), f"{train_dir}/../{train_dir.name}", str(root)]
    assert training_folders(twice) == ([train_dir], [str(sample_dir), str(root)])


@pytest.mark.slow  # long (≈ 50 s on 2 cores: eight launches): make test-slow runs it; the fast guards are
# test_a_run_folders_record_names_each_jobs_latest_run_... and test_a_point_a_relaunched_sweep_resumes_...
def test_a_relaunched_sample_or_evaluation_continues_its_mlflow_run_and_other_settings_open_a_new_one(
        store, tmp_path, monkeypatch):
    """A killed or failed launch left its run ``RUNNING``/``FAILED`` beside a new run of the relaunch that did the
    work: one folder, two dashboard rows. The relaunch with the same settings now continues the run; other
    settings, or ``resume=false``, open a new one (their numbers are other numbers)."""
    from mlflow import MlflowClient

    from spread.commands.evaluate import evaluate
    from spread.commands.sample import sample
    from spread.tracking import mlflow_store

    root, _, train_dir, _ = store
    uri = f"sqlite:///{tmp_path}/relaunch.db"  # a store of its own: the module's store keeps one run per job
    logger = ["logger=mlflow", f"logger.tracking_uri={uri}"]
    out, data = tmp_path / "s", root / "ds" / "data"

    def launch(*more):
        sample(compose("sample", f"ckpt={train_dir / 'checkpoints' / 'last.ckpt'}", f"data.root={data}",
                       f"out_dir={out}", *FAST_SAMPLE, "renders=0", "samples_per_graph=2", "experiment_name=relaunch",
                       *logger, *more))

    client = MlflowClient(tracking_uri=uri)

    def runs(job: str) -> list:
        found = client.search_runs([e.experiment_id for e in client.search_experiments()],
                                   order_by=["attributes.start_time ASC"])
        return [r for r in found if r.data.tags["spread.job_type"] == job]

    def died(*_args, **_kwargs):
        raise RuntimeError("killed after the work")

    with monkeypatch.context() as patched:
        patched.setattr(mlflow_store, "log_sampling", died)
        with pytest.raises(RuntimeError, match="killed"):
            launch()
    (first,) = runs("sample")
    assert first.info.status == "FAILED" and "sampling/samples" not in first.data.metrics
    launch()  # the same settings: the run goes on and finishes
    (again,) = runs("sample")
    assert again.info.run_id == first.info.run_id and again.info.status == "FINISHED"
    assert again.data.tags["spread.launches"] == "2" and again.data.metrics["sampling/written_this_run"] == 0
    assert json.loads((out / "mlflow_run.json").read_text())["run_id"] == first.info.run_id
    launch("seed=5")  # another seed: other scenes, a new run
    launch("seed=5")  # ... which its relaunch continues
    launch("seed=5", "resume=false")  # a redo from scratch: a new run again
    launch("seed=5", "logger.run_name=renamed")  # the same scenes, another record (name, params): a new run
    found = runs("sample")
    assert len(found) == 4 and [r.info.status for r in found] == ["FINISHED"] * 4
    assert [r.data.tags["spread.launches"] for r in found] == ["2", "2", "1", "1"]
    assert found[1].data.params["seed"] == found[2].data.params["seed"] == "5"
    assert found[3].info.run_name == "renamed" and found[3].data.params["logger.run_name"] == "renamed"

    # the sampling folder holds its own evaluation: each job continues its own run, launched in turns
    evaluation = [f"scenes={out / 'scenes'}", f"reference={data}", f"out_dir={out}", "renders=0",
                  "protocol.stability_runs=1", "fid.enabled=false", "progress=false", "experiment_name=relaunch",
                  *logger]
    evaluate(compose("evaluate", *evaluation))
    launch("seed=5", "logger.run_name=renamed")
    evaluate(compose("evaluate", *evaluation))
    (evaluated,) = runs("evaluate")
    assert evaluated.data.tags["spread.launches"] == "2" and evaluated.info.status == "FINISHED"
    assert len(runs("sample")) == 4 and runs("sample")[3].data.tags["spread.launches"] == "2"
    launch("seed=5")  # the settings of a run before the renamed one: that run goes on
    assert len(runs("sample")) == 4 and runs("sample")[2].data.tags["spread.launches"] == "2"
    next(iter(sorted((out / "scenes").glob("*.npz")))).unlink()  # other scenes: other numbers, a new run
    evaluate(compose("evaluate", *evaluation))
    assert len(runs("evaluate")) == 2
    # the folder's evaluations left its record naming their runs; an evaluation of its scenes elsewhere is still
    # told the sampling run that made them (it was told the folder's own evaluation's run)
    assert json.loads((out / "mlflow_run.json").read_text())["run_id"] == runs("evaluate")[1].info.run_id
    evaluate(compose("evaluate", *evaluation[:2], f"out_dir={tmp_path / 'elsewhere'}", *evaluation[3:]))
    elsewhere = [r for r in runs("evaluate") if r.data.params["out_dir"] == str(tmp_path / "elsewhere")]
    assert len(elsewhere) == 1
    assert elsewhere[0].data.tags["spread.sampling_run_id"] == runs("sample")[2].info.run_id
    assert elsewhere[0].data.tags["spread.training_run_id"] == runs_by_job(store[1])["train"].info.run_id


def test_a_run_folders_record_names_each_jobs_latest_run_and_reads_an_older_record_as_its_one_run(tmp_path):
    """``mlflow_run.json`` names the folder's latest run (whose numbers it holds) and, per job type, that job's latest
    run; a record written before the per-job entries names its one run for any job; a damaged one names none."""
    from spread.results.store import made_the_folder
    from spread.tracking.mlflow_store import RUN_FILE, job_run_id, write_run_file

    write_run_file(tmp_path, "sqlite:///x.db", "1", "s1", "sample")
    write_run_file(tmp_path, "sqlite:///x.db", "2", "e1", "evaluate")
    assert (job_run_id(tmp_path, "sample"), job_run_id(tmp_path, "evaluate"), job_run_id(tmp_path, "train")) == \
        ("s1", "e1", None)
    assert made_the_folder("e1", tmp_path) and not made_the_folder("s1", tmp_path)
    write_run_file(tmp_path, "sqlite:///x.db", "1", "s2", "sample")
    assert (job_run_id(tmp_path, "sample"), job_run_id(tmp_path, "evaluate")) == ("s2", "e1")
    (tmp_path / RUN_FILE).write_text(json.dumps({"tracking_uri": "sqlite:///x.db", "run_id": "old"}))
    assert job_run_id(tmp_path, "sample") == job_run_id(tmp_path, "evaluate") == "old"
    write_run_file(tmp_path, "sqlite:///x.db", "2", "e2", "evaluate")  # the older record's job is not known
    assert (job_run_id(tmp_path, "sample"), job_run_id(tmp_path, "evaluate")) == (None, "e2")
    (tmp_path / RUN_FILE).write_text("{")
    assert job_run_id(tmp_path, "sample") is None
    write_run_file(tmp_path, "sqlite:///x.db", "1", "s3", "sample")  # a damaged record is replaced
    assert job_run_id(tmp_path, "sample") == "s3"
