"""Hostile inputs, round 15 (docs/robustness.md): a checkpoint that cannot sample is refused before a finished folder
is touched; a link planted in a run folder is refused; settings that could never run or that hang are refused by
key; a hand-damaged evaluation record is a failed scene, never a traceback or a wiped aggregate; a guidance setting
its mode does not read is no part of the identity; a release file's weights that hold no values are named."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import time
from pathlib import Path

import pytest
import torch

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset, sample_in_process, train_in_process, user_error


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("r15data"))


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory) -> Path:
    """A base model's run folder after 2 training steps (checkpoints/last.ckpt)."""
    out = tmp_path_factory.mktemp("r15run") / "run"
    train_in_process(out, "experiment=quick", "model.variant=base", f"data.root={dataset}", "trainer.max_time=null",
                     "trainer.max_steps=2", *SMALL_MODEL, *FAST_TRAIN)
    return out


@pytest.fixture(scope="module")
def sampled(dataset, run, tmp_path_factory) -> Path:
    """A finished sampling folder (3 scenes) of ``run``'s checkpoint."""
    out = tmp_path_factory.mktemp("r15s") / "s"
    sample_in_process(f"ckpt={run / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}", f"out_dir={out}",
                      "renders=0")
    return out


def folder_state(out: Path) -> dict:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name != ".spread.lock"}  # the lock says who held it last


def edited_checkpoint(source: Path, target: Path, edit) -> Path:
    checkpoint = torch.load(source, weights_only=True)
    edit(checkpoint)
    torch.save(checkpoint, target)
    return target


def _nan_weights(c):
    for value in c["state_dict"].values():
        if value.is_floating_point() and value.numel() > 10:
            value.fill_(float("nan"))


def _meta_weights(c):
    sd = c["state_dict"]
    for key, value in list(sd.items()):
        if value.is_floating_point() and value.numel() > 10:
            sd[key] = torch.empty(value.shape, dtype=value.dtype, device="meta")


BAD_CHECKPOINTS = [
    ("nearest", lambda c: c["hyper_parameters"]["config"].__setitem__("nearest", "bogus"), "unknown search 'bogus'"),
    ("prediction", lambda c: c["hyper_parameters"].__setitem__("prediction", "bogus"), "unknown prediction 'bogus'"),
    ("schedule", lambda c: c["hyper_parameters"].__setitem__("beta_schedule", "bogus"),
     "beta_schedule='bogus': not a beta schedule"),
    ("steps", lambda c: c["hyper_parameters"].__setitem__("diffusion_steps", 10 ** 12),
     "diffusion_steps=1000000000000: expected a whole number in [1, 100,000]"),
    ("nan", _nan_weights, "holds non-finite values"),
    ("meta", _meta_weights, "is on PyTorch's meta device"),
]


def test_a_checkpoint_whose_hyperparameters_or_weights_cannot_sample_is_refused_before_the_finished_folder_is_touched(
        dataset, run, sampled, tmp_path):
    """Each deleted the finished folder's scenes, then failed (naming an output file, or in a traceback), or held
    the command for ever (``diffusion_steps: 1e12``: diffusers' Python loop over the steps)."""
    from spread.safe_load import CheckpointMismatchError

    before = folder_state(sampled)
    for name, edit, says in BAD_CHECKPOINTS:
        ckpt = edited_checkpoint(run / "checkpoints" / "last.ckpt", tmp_path / f"{name}.ckpt", edit)
        started = time.perf_counter()
        with pytest.raises(CheckpointMismatchError, match=re.escape(f"{ckpt}: ") + ".*" + re.escape(says)):
            sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={sampled}", "renders=0")
        assert time.perf_counter() - started < 60, name
        assert folder_state(sampled) == before, name
    line, _ = user_error("spread-sample", f"ckpt={tmp_path / 'nan.ckpt'}", f"data.root={dataset}",
                         f"out_dir={sampled}", "workers=0", "logger=none")
    assert "holds non-finite values (NaN or infinity); refused before any work" in line
    assert folder_state(sampled) == before


def test_a_model_refuses_a_schedule_it_cannot_make_at_once():
    from spread.model import SceneDiffusion

    started = time.perf_counter()
    with pytest.raises(ValueError, match=r"diffusion_steps=1000000000000.0: expected a whole number"):
        SceneDiffusion(variant="base", diffusion_steps=1e12)
    with pytest.raises(ValueError, match="diffusion_steps=0"):
        SceneDiffusion(variant="base", diffusion_steps=0)
    assert time.perf_counter() - started < 30
    assert SceneDiffusion(variant="base", diffusion_steps=100.0, beta_schedule="linear").noise_schedule.config[
        "num_train_timesteps"] == 100


def test_a_link_planted_inside_a_run_folder_is_refused_and_its_target_left_as_it_was(dataset, run, sampled, tmp_path):
    """``scenes`` linked to another folder: spread-sample deleted that folder's files and wrote its own there;
    ``.hydra`` linked: Hydra overwrote the target's config.yaml."""
    victim = tmp_path / "victim"
    shutil.copytree(dataset / "test", victim)
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "config.yaml").write_text("precious\n")
    out = tmp_path / "x"
    out.mkdir()
    os.symlink(victim, out / "scenes")
    kept = folder_state(victim)
    from spread.io import UnsafeOutputError

    with pytest.raises(UnsafeOutputError, match=re.escape(f"{out / 'scenes'}: a symbolic link (to {victim}) inside "
                                                          f"the run folder")):
        sample_in_process(f"ckpt={run / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}", f"out_dir={out}",
                          "renders=0")
    os.symlink(tmp_path / "cfg", out / ".hydra")
    line, _ = user_error("spread-sample", f"ckpt={run / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}",
                         f"out_dir={out}", "workers=0", "logger=none")
    assert line.startswith(f"spread-sample: out_dir={out}: {out / '.hydra'}: a symbolic link"), line
    assert folder_state(victim) == kept and (tmp_path / "cfg" / "config.yaml").read_text() == "precious\n"
    assert sorted(p.name for p in out.iterdir()) == [".hydra", "scenes"]
    # a run folder that is itself a link is a user's choice: allowed
    os.symlink(sampled, tmp_path / "linked")
    from spread.cli.errors import out_dir_problem

    assert out_dir_problem(str(tmp_path / "linked")) is None


@pytest.mark.parametrize("make, says", [
    (lambda: __import__("spread.runtime.ray", fromlist=["RaySettings"]).RaySettings(num_cpus=0),
     "ray.num_cpus=0: expected a whole number ≥ 1"),
    (lambda: __import__("spread.evaluation.protocol", fromlist=["EvalProtocol"]).EvalProtocol(
        stability_jitter=math.inf), "protocol.stability_jitter=inf: expected a finite number"),
    (lambda: __import__("spread.evaluation.protocol", fromlist=["EvalProtocol"]).EvalProtocol(
        collision_threshold=math.nan), "protocol.collision_threshold=nan: expected a finite number"),
])
def test_settings_that_never_end_or_fail_every_scene_are_refused_by_key(make, says):
    """``ray.num_cpus=0`` started a cluster on which nothing could run (the command waited for ever);
    ``stability_jitter=inf`` deleted a finished evaluation's lines, then failed Stability on every scene."""
    with pytest.raises(ValueError, match=re.escape(says)):
        make()


def test_spread_evaluate_with_ray_num_cpus_zero_is_refused_in_one_line(dataset, tmp_path):
    line, proc = user_error("spread-evaluate", f"scenes={dataset / 'test'}", f"reference={dataset}",
                            f"out_dir={tmp_path / 'e'}", "ray.num_cpus=0", "logger=none", timeout=120)
    assert "ray.num_cpus=0: expected a whole number ≥ 1" in line
    assert not (tmp_path / "e").exists()


def test_spread_sample_refuses_zero_samples_or_batch_before_reading_the_checkpoint(dataset, tmp_path):
    from spread.configs import compose, to_object

    for key in ("samples_per_graph", "batch_size"):
        with pytest.raises(ValueError, match=re.escape(f"{key}=0: expected a whole number ≥ 1")):
            to_object(compose("sample", [f"ckpt={tmp_path / 'none.ckpt'}", f"data.root={dataset}",
                                         f"out_dir={tmp_path / 's'}", f"{key}=0"]))


def test_hand_damaged_evaluation_records_are_failed_scenes_and_renders_come_from_the_scene_files(dataset, tmp_path):
    """Each damage gave a traceback on every relaunch (a JSON array line, a state missing its keys, a number or lists
    where states go, ``1e300``), or wiped the dataset's GRecall (counts of -1000); a record's ``file`` drew another
    file under the scene's name."""
    scenes = tmp_path / "scenes"
    scenes.mkdir()
    for path in sorted(dataset.glob("*/*.npz")):
        shutil.copy(path, scenes / path.name)
    out = tmp_path / "e"
    overrides = [f"scenes={scenes}", f"reference={dataset}", f"out_dir={out}", "metrics=[grecall]",
                 "fid.enabled=false", "logger=none", "progress=false", "renders=0"]
    import ray

    ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False)  # one Ray for the three
    try:  # evaluations (spread.runtime.ray uses a caller's Ray as it is)
        evaluate_damaged(dataset, scenes, out, overrides)
    finally:
        ray.shutdown()


def evaluate_damaged(dataset, scenes, out, overrides):
    import numpy as np
    from PIL import Image

    from spread.assets import AssetLibrary
    from spread.configs import compose, to_object
    from spread.evaluation import run_evaluation
    from spread.io import read_jsonl
    from spread.render import render_topdown
    from spread.scene import read_scene

    first = run_evaluation(to_object(compose("evaluate", overrides))).metrics
    assert first["n_failed"] == 0
    lines = read_jsonl(out / "per_scene.jsonl")
    state = lines[0]["state"]["grecall"]
    damages = [{"nope": 1}, 5, {k: 1e300 for k in state}, {k: [v, v, v] for k, v in state.items()},
               {k: -1000 for k in state}]
    assert len(lines) > len(damages)
    records = [dict(r) for r in lines]
    for record, damaged in zip(records, damages):
        record["state"] = {**record["state"], "grecall": damaged}
    (out / "per_scene.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records) + "[1, 2]\n")
    metrics = run_evaluation(to_object(compose("evaluate", overrides))).metrics
    assert sorted(f["scene_id"] for f in metrics["failed"]) == sorted(r["scene_id"] for r in lines[:len(damages)])
    assert metrics["n_failed"] == len(damages) and metrics["n_evaluated"] == len(lines) - len(damages)
    kept = [r["state"]["grecall"] for r in lines[len(damages):]]
    matches, pairs = (sum(s[k] for s in kept) for k in ("matches", "pairs"))  # the other scenes' sums, as they were
    assert metrics["grecall"] == pytest.approx(matches / pairs)
    # renders: from the scene file of that id, never from the record's ``file``
    records = [dict(r) for r in lines]
    records[0]["file"] = str(sorted((dataset / "test").glob("*.npz"))[-1])
    records[1]["file"] = 5
    (out / "per_scene.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
    overrides[overrides.index("renders=0")] = "renders=2"
    run_evaluation(to_object(compose("evaluate", overrides)))
    library = AssetLibrary.load(dataset / "assets")
    for record in sorted(lines, key=lambda r: r["scene_id"])[:2]:
        drawn = np.asarray(Image.open(out / "renders" / f"{record['scene_id']}.png").convert("RGB"))
        own = render_topdown(read_scene(scenes / f"{record['scene_id']}.npz", assets=library), library)
        assert np.array_equal(drawn, own), record["scene_id"]


def test_guidance_settings_its_mode_does_not_read_are_no_part_of_its_identity():
    """``guidance=paper guidance.iterations=7 guidance.denoise_every=3`` resampled every scene to the same bytes."""
    from spread.guidance import GuidanceConfig
    from spread.runtime.fingerprint import identity_changes

    paper = GuidanceConfig(mode="paper")
    assert GuidanceConfig(mode="paper", iterations=7, denoise_every=3, clip=False).fingerprint() == paper.fingerprint()
    assert GuidanceConfig(mode="paper", iterations=7).label == paper.label
    assert GuidanceConfig(mode="paper", inner_steps=2).fingerprint() != paper.fingerprint()
    refine = GuidanceConfig(mode="refine")
    assert GuidanceConfig(mode="refine", start=0.5, last_steps=3, inner_steps=2).fingerprint() == refine.fingerprint()
    assert GuidanceConfig(mode="refine", iterations=7).fingerprint() != refine.fingerprint()
    assert "iterations=7" in GuidanceConfig(mode="refine", iterations=7).label
    # an identity recorded with every setting (before) reads as today's
    recorded = {"guidance": {**paper.to_dict(), **paper.weights(nonzero=True)}}
    recorded["guidance"].pop("terms")
    for key in ("collision", "gravity", "relation"):
        recorded["guidance"][key] = paper.weight(key)
    assert "iterations" in recorded["guidance"]
    assert identity_changes(recorded, {"guidance": paper.fingerprint()}) == []
    assert identity_changes(recorded, {"guidance": GuidanceConfig(mode="paper", start=0.5).fingerprint()}) == [
        "guidance.start"]


def test_a_release_file_whose_weights_hold_no_values_or_a_weight_twice_is_refused_by_name(tmp_path):
    """A meta tensor: a traceback from ``.item()``; a 1.6 kB expanded tensor: an allocation of 40 TB; ``x`` and
    ``_orig_mod.x`` both: one was dropped unseen (a checkpoint of zeros written)."""
    from spread.cli.release_ckpt import check_release_weights
    from spread.methods.release_network import ReleaseCheckpointError

    cases = {"meta": ({"network.a": torch.zeros(2, device="meta")}, "weight 'a' is on PyTorch's meta device"),
             "expand": ({"network.a": torch.zeros(1).expand(10 ** 13)},
                        "weight 'a' of shape (10000000000000,) reads 40,000,000,000,000 bytes from a storage of 4"),
             "twice": ({"_orig_mod.network.a": torch.ones(2), "network.a": torch.zeros(2)},
                       "'model' holds weight 'network.a' twice, as '_orig_mod.network.a' too")}
    for name, (model, says) in cases.items():
        path = tmp_path / f"{name}.pth"
        torch.save({"model": model}, path)
        assert path.stat().st_size < 10_000
        with pytest.raises(ReleaseCheckpointError, match=re.escape(says)):
            check_release_weights(str(path), use_ema=False)


def test_a_refused_ablation_relaunch_leaves_the_folders_record_and_a_run_folder_is_no_ablation(dataset, run, tmp_path):
    """The stage lists were checked after ``.hydra/config.yaml`` was rewritten: the folder then named settings its
    results were never made with. A training run's folder as ``out_dir`` had its record replaced, and the stages
    written beside its checkpoints."""
    from spread.commands.ablate import ablate

    from helpers import compose

    out = tmp_path / "a"
    (out / ".hydra").mkdir(parents=True)
    (out / ".hydra" / "config.yaml").write_text("before: true\n")
    (out / "ablation.json").write_text('{"stages": {}}')
    common = ["variants=[base]", f"train.ckpt.base={run / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}",
              "logger=none", "figures=false"]
    for setting, says in [("stages.max_concurrent=0", "stages.max_concurrent=0: expected a whole number ≥ 1"),
                          ("stages.train_concurrent=1.5", "stages.train_concurrent=1.5: expected a whole number ≥ 1"),
                          ("figures=maybe", "figures='maybe': expected true or false")]:  # each was taken silently
        with pytest.raises(ValueError, match=re.escape(says)):
            ablate(compose("ablate", *common, f"out_dir={out}", setting))
    with pytest.raises(ValueError, match=r"^sample/base: its overrides .*unknown sampler 'nope'"):
        ablate(compose("ablate", *common, f"out_dir={out}", 'sample.extra=["sampler.kind=nope"]'))
    assert (out / ".hydra" / "config.yaml").read_text() == "before: true\n"
    before = folder_state(run)
    with pytest.raises(ValueError, match=re.escape(f"out_dir={run}: holds a training run")):
        ablate(compose("ablate", *common, f"out_dir={run}"))
    assert folder_state(run) == before


def test_spread_sweep_refuses_a_metric_no_point_reports_and_a_folder_of_another_kind_before_any_trial(
        dataset, run, tmp_path):
    from spread.commands.sweep import sweep

    common = [f"ckpt={run / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}", "+sweep=guidance_grid",
              "guidance.collision=0.0,0.0075", "logger=none"]
    with pytest.raises(ValueError, match=r"metric=grecal: no point reports it \(a sampling sweep's points report "
                                         r"grecall, col_mesh"):
        sweep([*common, f"out_dir={tmp_path / 'w'}", "metric=grecal"])
    with pytest.raises(ValueError, match=re.escape(f"out_dir={dataset}: holds a dataset")):
        sweep([*common, f"out_dir={dataset}"])
    with pytest.raises(ValueError, match=re.escape("seed is swept and seeds=2: a point samples the seeds from its")):
        sweep([*common, "seed=0,1", "seeds=2", f"out_dir={tmp_path / 'w'}"])
    assert not (tmp_path / "w").exists() and not (dataset / "points").exists()


def test_ctrl_c_ends_spread_sweep_as_interrupted_with_no_table(monkeypatch, capsys):
    """Ray Tune's own SIGINT handler made ``tuner.fit()`` return, and the sweep wrote the points finished so far as
    its table, exit 0. Now Ctrl-C is a KeyboardInterrupt out of the trials (next test) and ends the command."""
    import spread.commands.sweep
    from spread.cli.sweep import main

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(spread.commands.sweep, "sweep", interrupted)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.delenv("SPREAD_DEBUG", raising=False)
    with pytest.raises(SystemExit) as stop:
        main(["out_dir=x"])
    assert stop.value.code == 130
    assert capsys.readouterr().err.strip() == ("spread-sweep: interrupted (Ctrl-C); a relaunch goes on from the points "
                                               "recorded")


TUNE_CTRL_C = """
import os, signal, sys, threading, time
from ray import tune
from spread.experiments.sweep import tune_leaves_ctrl_c
from spread.runtime.ray import RaySettings, ray_session

def trainable(config):
    time.sleep(120)
    tune.report({"x": 1})

signal.signal(signal.SIGINT, signal.default_int_handler)  # as from a terminal (a test worker's children ignore it)
with ray_session(RaySettings(num_cpus=1, object_store_memory=80 * 1024 * 1024), owner=None):
    try:
        threading.Timer(6.0, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
        with tune_leaves_ctrl_c():
            tune.Tuner(trainable, tune_config=tune.TuneConfig(num_samples=1),
                       run_config=tune.RunConfig(storage_path=sys.argv[1], name="t", verbose=0)).fit()
        print("fit returned", flush=True)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
print("handler restored:", os.environ.get("TUNE_DISABLE_SIGINT_HANDLER") is None, flush=True)
"""


@pytest.mark.timeout(180)
def test_ray_tune_leaves_ctrl_c_to_the_sweep_while_its_trials_run(tmp_path):
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "TUNE_DISABLE_SIGINT_HANDLER"}
    proc = subprocess.run([sys.executable, "-c", TUNE_CTRL_C, str(tmp_path / "tune")], capture_output=True, text=True,
                          timeout=170, env=env)
    assert "interrupted" in proc.stdout.splitlines(), proc.stdout[-2000:] + proc.stderr[-3000:]
    assert "handler restored: True" in proc.stdout


@pytest.mark.parametrize("uri, says", [
    ("file:///{tmp}/fs", "a file store, which MLflow keeps in maintenance mode"),
    ("mysql://u@127.0.0.1:1/db", "its database driver is not installed (no module named 'MySQLdb')"),
    ("http://127.0.0.1:1", "an MLflow server already"),
])
def test_spread_dashboard_names_a_store_its_server_cannot_serve_before_it_prints_a_url(uri, says, tmp_path):
    """Each printed ``open http://…`` and then MLflow's traceback (26–47 lines)."""
    from helpers import free_port

    uri = uri.format(tmp=tmp_path)
    line, proc = user_error("spread-dashboard", f"tracking_uri={uri}", f"port={free_port()}", timeout=60)
    assert line.startswith(f"spread-dashboard: tracking_uri={uri}: {says}"), line
    assert "open http" not in proc.stdout


def test_a_sweep_point_whose_metrics_json_was_hand_damaged_is_not_reused(tmp_path):
    """A NaN GRecall and a count of text: the sweep re-used the point (shown ok, GRecall –, the star moved) where
    spread-report refuses the file; the point is resumed now, and its evaluation writes the file again."""
    from spread.experiments.points import damaged_metrics

    path = tmp_path / "metrics.json"
    path.write_text(json.dumps({"grecall": 0.5, "n_scenes": 3, "n_failed": 0}))
    assert damaged_metrics(tmp_path) is None
    path.write_text(json.dumps({"grecall": float("nan"), "n_scenes": 3}))
    assert "its metrics.json is damaged" in damaged_metrics(tmp_path) and "'grecall'" in damaged_metrics(tmp_path)
    path.write_text(json.dumps({"grecall": 0.5, "n_scenes": "x"}))
    assert "key 'n_scenes' is 'x'" in damaged_metrics(tmp_path)
