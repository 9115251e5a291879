"""Multi-run commands on the dashboard (issue 31 item 2; spread.tracking.parent): the trials' stores pinned to
absolute paths in the driver, one MLflow parent run per sweep / ablation / comparison with every trial's or
stage's run nested under it, and re-used points logged as such.

Fast: the overrides that pin the stores; an ablation's run is the parent of the runs its stages open (here, in
a subprocess, as a launched training stage). Slow (a dataset, a tiny checkpoint, real sampling): ``spread-sweep
… logger=mlflow`` with two points, run from another folder with a relative ``paths.runs_dir``, and its identical
relaunch.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import FAST_TRAIN, SCRIPTS, SMALL_MODEL, make_dataset, train_in_process

ENV = {**os.environ, "WANDB_MODE": "disabled", "HYDRA_FULL_ERROR": "1", "OMP_NUM_THREADS": "1"}


def runs_of(uri: str) -> list:
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    experiments = [e.experiment_id for e in client.search_experiments()]
    return client.search_runs(experiments, max_results=1000)


def test_relative_stores_are_pinned_to_absolute_paths_in_the_driver(tmp_path, monkeypatch):
    from spread.configs import compose
    from spread.tracking.parent import absolute_tracking_overrides

    monkeypatch.chdir(tmp_path)
    cfg = compose("sample", ["ckpt=c", "data.root=/d", "logger=mlflow", "paths.runs_dir=my runs", "out_dir=x"])
    extra = absolute_tracking_overrides(cfg)
    assert extra == [f"paths.runs_dir='{tmp_path}/my runs'", f"logger.tracking_uri='sqlite:///{tmp_path}/my runs/mlflow.db'"]
    again = compose("sample", ["ckpt=c", "data.root=/d", "logger=mlflow", "paths.runs_dir=my runs", "out_dir=x", *extra])
    assert again.logger.tracking_uri == f"sqlite:///{tmp_path}/my runs/mlflow.db"
    assert absolute_tracking_overrides(again) == []  # already absolute: nothing moves
    # no MLflow: nothing a trial writes depends on them (and a training point's identity stays as it was)
    assert absolute_tracking_overrides(compose("sample", ["ckpt=c", "data.root=/d", "logger=none", "out_dir=x"])) == []


def test_an_ablation_run_is_the_parent_of_its_stages_runs_in_this_and_other_processes(tmp_path, monkeypatch):
    """run_stages_command (spread-ablate's and spread-compare's frame) with logger=mlflow: the ablation's run is
    tagged as a parent (kind, name, out_dir); a run a stage opens in this process and one a launched stage opens
    in a subprocess are nested under it; a run opened after the command is not."""
    from spread.commands.ablate import ablation_spec, run_stages_command
    from spread.configs import compose
    from spread.tracking import mlflow_store

    monkeypatch.chdir(tmp_path)
    cfg = compose("ablate", ["+preset=quick", "logger=mlflow", f"paths.runs_dir={tmp_path}/runs", "name=tiny",
                             "recipe=null"])
    spec = ablation_spec(cfg)
    uri = mlflow_store.resolve_tracking_uri(cfg.logger.tracking_uri)
    stage = ("from spread.tracking import mlflow_store as m; r = m.open_run({'name': 'mlflow', 'tracking_uri': %r},"
             " 'train', %r, {}, %r); r.finish()")

    def body(commands, logger, config, run):
        here = mlflow_store.open_run(logger, "sample", tmp_path / "stage_a", {}, spec.group)
        here.finish()
        code = stage % (uri, str(tmp_path / "stage_b"), spec.group)
        subprocess.run([sys.executable, "-c", code], check=True, env=os.environ.copy(), timeout=120)
        return run.run_id

    parent_id = run_stages_command(cfg, spec, "ablate", "ablation/tiny", body)
    after = mlflow_store.open_run(cfg.logger, "sample", tmp_path / "after", {}, spec.group)
    after.finish()
    runs = {r.info.run_id: r for r in runs_of(uri)}
    parent = runs[parent_id]
    assert parent.data.tags["spread.kind"] == "ablation" and parent.data.tags["spread.name"] == "tiny"
    assert parent.data.tags["spread.out_dir"] == str(spec.out_dir.resolve()) and parent.info.status == "FINISHED"
    children = [r for r in runs.values() if r.data.tags.get("mlflow.parentRunId") == parent_id]
    assert sorted(r.data.tags["spread.job_type"] for r in children) == ["sample", "train"]
    assert all(r.info.experiment_id == parent.info.experiment_id for r in children)
    assert "mlflow.parentRunId" not in runs[after.run_id].data.tags


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """12 generated rooms (3 test graphs) and a 2-step checkpoint of the shrunken model."""
    root = tmp_path_factory.mktemp("dashdata")
    data = make_dataset(root)
    train_in_process(root / "train", f"data.root={data}", "experiment=quick", *SMALL_MODEL, *FAST_TRAIN,
                     "trainer.max_steps=2", "trainer.max_time=null")
    return {"data": data, "ckpt": root / "train" / "checkpoints" / "last.ckpt"}


@pytest.mark.slow
def test_spread_sweep_with_mlflow_logs_one_parent_and_every_point_nested_also_when_reused(tiny, tmp_path):
    """Run from another folder with relative paths.runs_dir=runs: the store there holds one parent run (kind
    sweep) and two nested trial runs with their metrics; the identical relaunch (both points re-used, no trial
    sampling) adds a second parent run with two children tagged re-used, each linked to the run that made it."""
    args = [f"ckpt={tiny['ckpt']}", f"data.root={tiny['data']}", "+sweep=guidance_grid",
            "guidance.collision=0.0,0.0075", "guidance.gravity=0.001", "guidance.relation=0.001",
            "guidance.iterations=2", "sampler.steps=4", "batch_size=2", "renders=0", "logger=mlflow",
            "evaluation.protocol.stability_runs=1", "evaluation.fid.enabled=false", "num_cpus=2",
            "max_concurrent=2", "paths.runs_dir=runs", "out_dir=D", "name=dash"]
    for _ in range(2):
        proc = subprocess.run([str(SCRIPTS / "spread-sweep"), *args], env=ENV, cwd=tmp_path, capture_output=True,
                              text=True, timeout=900)
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    uri = f"sqlite:///{tmp_path}/runs/mlflow.db"
    runs = runs_of(uri)
    parents = sorted((r for r in runs if r.data.tags.get("spread.kind") == "sweep"), key=lambda r: r.info.start_time)
    assert len(parents) == 2 and all(p.data.tags["spread.name"] == "dash" for p in parents)
    first, second = ([r for r in runs if r.data.tags.get("mlflow.parentRunId") == p.info.run_id] for p in parents)
    assert len(first) == 2 and len(second) == 2
    assert all("grecall" in r.data.metrics and "grecall_lo" in r.data.metrics and "col_mesh" in r.data.metrics
               for r in first + second)
    assert not any(r.data.tags.get("spread.reused") for r in first)
    assert all(r.data.tags.get("spread.reused") == "true" for r in second)
    made = {r.data.tags["spread.point"]: r.data.tags.get("spread.made_by_run_id") for r in second}
    by_folder = {Path(r.data.params["out_dir"]).name: r.info.run_id for r in first}
    assert made == by_folder
    assert {r.data.metrics["grecall"] for r in first} == {r.data.metrics["grecall"] for r in second}
    assert not list((tmp_path / "D").rglob("mlflow.db"))
