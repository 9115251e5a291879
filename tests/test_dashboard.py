"""``logger=mlflow``: a tiny train and a sample + evaluate in one SQLite store, read back through MLflow's
client and through ``spread-dashboard`` (the real ``mlflow server``) over HTTP on localhost."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import time
import urllib.request
from pathlib import Path

import pytest

from helpers import FAST_SAMPLE, FAST_TRAIN, SCRIPTS, SMALL_MODEL, compose, make_dataset, train_in_process


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """(folder, store URI, training run folder, sampling run folder): 6 training steps and one sampling run with
    ``evaluate=true``, both with ``logger=mlflow`` into ``<folder>/mlflow.db``."""
    from spread.experiments.commands import sample

    root = tmp_path_factory.mktemp("mlstore")
    data = make_dataset(root / "ds", rooms=8)
    uri = f"sqlite:///{root}/mlflow.db"
    logger = ["logger=mlflow", f"logger.tracking_uri={uri}"]
    train_dir = root / "train"
    train_in_process(train_dir, "experiment=quick", f"data.root={data}", "trainer.max_time=null",
                     "trainer.max_steps=6", "trainer.log_every_n_steps=1", "trainer.check_val_every_n_epoch=1",
                     *SMALL_MODEL, *FAST_TRAIN, *logger)
    sample_dir = root / "sample"
    sample(compose("sample", f"ckpt={train_dir / 'checkpoints' / 'last.ckpt'}", f"data.root={data}",
                   f"out_dir={sample_dir}", *FAST_SAMPLE, "evaluate=true", "evaluation.protocol.stability_runs=1",
                   "evaluation.fid.enabled=false", "experiment_name=tiny_sample", *logger))
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
    assert {"val/loss", "train/grad_norm"} <= set(train.data.metrics)
    assert any(k.startswith("lr-") for k in train.data.metrics)
    assert train.data.params["model.variant"] == train.data.tags["spread.variant"]
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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


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


def test_dashboard_refuses_unknown_arguments_by_name():
    proc = subprocess.run([str(SCRIPTS / "spread-dashboard"), "prot=5"], capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0 and "'prot=5'" in proc.stderr
