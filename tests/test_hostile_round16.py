"""Hostile inputs, round 16 (docs/robustness.md): a study's row asked twice is refused, never collapsed; a sweep
point's record that is a folder is named before any trial."""

from __future__ import annotations

import re

import pytest

from helpers import compose, user_error


@pytest.mark.parametrize("rows, says", [
    ("variants=[base,geometry,base]", "variants: 'base' is listed twice in ['base', 'geometry', 'base']; give each row once"),
])
def test_an_ablation_row_asked_twice_is_refused_by_key(rows, says, tmp_path):
    """``variants=[base,base]`` made a table of one row: the list asked for something the table did not hold."""
    from spread.commands.ablate import ablation_spec

    with pytest.raises(ValueError, match=f"^{re.escape(says)}$"):
        ablation_spec(compose("ablate", rows, "data.root=/d", f"out_dir={tmp_path / 'a'}"))
    line, _ = user_error("spread-ablate", rows, f"out_dir={tmp_path / 'a'}", "logger=none", cwd=tmp_path)
    assert line == f"spread-ablate: {says} (HYDRA_FULL_ERROR=1 shows the traceback)", line
    assert list(tmp_path.iterdir()) == []


def test_a_comparison_row_asked_twice_is_refused_by_key(tmp_path):
    from spread.commands.compare import compare_spec

    with pytest.raises(ValueError, match=r"^methods: 'atiss' is listed twice in \['atiss', 'spread', 'atiss'\]; "
                                         r"give each row once$"):
        compare_spec(compose("compare", "methods=[atiss,spread,atiss]", "data.root=/d", f"out_dir={tmp_path / 'c'}"))


@pytest.mark.parametrize("record", ["point.json", "metrics.json"])
def test_a_sweep_points_record_that_is_a_folder_is_named_before_any_trial(record, tmp_path):
    """A ``point.json`` replaced by a folder failed its trial in Ray's tracebacks (the redo could not clear it)."""
    from spread.commands.sweep import sweep

    (tmp_path / "d" / "test").mkdir(parents=True)
    (tmp_path / "c.ckpt").write_bytes(b"never read")
    bad = tmp_path / "w" / "points" / "p" / record
    bad.mkdir(parents=True)
    with pytest.raises(ValueError, match=f"^spread-sweep: {bad}: not a file \\(a point's record\\); remove it"):
        sweep([f"ckpt={tmp_path / 'c.ckpt'}", f"data.root={tmp_path / 'd'}", "+sweep=guidance_grid",
               "guidance.collision=0.0,0.0075", "logger=none", f"out_dir={tmp_path / 'w'}"])
    assert sorted(p.name for p in (tmp_path / "w").iterdir()) == ["points"]


@pytest.mark.parametrize("setting, says", [
    ("ray_train.num_workers=0", "ray_train.num_workers=0: expected a whole number ≥ 1"),
    ("ray_train.cpus_per_worker=0", "ray_train.cpus_per_worker=0: expected a number > 0"),
    ("ray_train.num_to_keep=0", "ray_train.num_to_keep=0: expected a whole number ≥ 1, or null for every checkpoint"),
    ("ray_train.max_failures=-2", "ray_train.max_failures=-2: expected a whole number ≥ -1"),
    ("ray_train.use_gpu=maybe", "ray_train.use_gpu='maybe': expected true or false"),
    ("+ray_train.bogus=1", "ray_train.bogus: not a Ray Train setting (known: address, num_cpus, num_workers"),
])
def test_spread_train_ray_refuses_a_ray_train_setting_by_key_before_its_record(setting, says, tmp_path):
    """``num_workers=0`` trained in the driver outside Ray Train's store; ``cpus_per_worker=0`` failed inside Ray
    after it started; an unknown key was a TypeError; each after the run's ``.hydra/config.yaml`` was rewritten."""
    from spread.training.ray_train import ray_train_settings

    with pytest.raises(ValueError, match=f"^{re.escape(says)}"):
        ray_train_settings(compose("train", "trainer=ray", "data.root=/d", setting))
    if setting.startswith("ray_train.num_workers"):  # the command line: one line, nothing made, Ray never started
        line, _ = user_error("spread-train-ray", "data.root=/nowhere", f"out_dir={tmp_path / 'run'}", setting,
                             cwd=tmp_path)
        assert line == f"spread-train-ray: {says} (HYDRA_FULL_ERROR=1 shows the traceback)", line
        assert list(tmp_path.iterdir()) == []


def test_a_cluster_address_where_nothing_answers_is_refused_by_a_probe_before_any_record(tmp_path):
    """``ray_train.address=127.0.0.1:1`` retried the GCS for minutes (past 300 s), after the run's record was
    rewritten; every command that joins a cluster (``ray.address``) asks the address first."""
    from helpers import free_port

    from spread.runtime.ray import RaySettings, address_problem, ray_session

    port = free_port()  # nothing listens there
    with pytest.raises(ValueError, match=f"^ray.address=127.0.0.1:{port}: nothing answers there \\("):
        with ray_session(RaySettings(address=f"127.0.0.1:{port}")):
            pass
    line, _ = user_error("spread-train-ray", "data.root=/nowhere", f"out_dir={tmp_path / 'run'}",
                         f"ray_train.address=127.0.0.1:{port}", cwd=tmp_path)
    assert line.startswith(f"spread-train-ray: ray_train.address=127.0.0.1:{port}: nothing answers there ("), line
    assert list(tmp_path.iterdir()) == []
    assert address_problem("auto") is None and address_problem("local") is None  # Ray's own to find


def test_a_reports_renders_are_of_the_scenes_its_numbers_measured(tmp_path):
    """A folder sampled again (seed 5) after its evaluation (seed 0): the page showed the new scenes' pictures beside
    the old scenes' numbers. Such renders are left out, named; renders of the measured sampling are shown."""
    import json

    from PIL import Image

    from spread.reporting.html_report import renders_of

    run = tmp_path / "s"
    (run / "renders").mkdir(parents=True)
    Image.new("RGB", (4, 4)).save(run / "renders" / "g0_k0.png")
    made = {"ckpt_sha256": "ab", "guidance": {"mode": "none"}, "sampling": {"seed": 0}}
    (run / "metrics.json").write_text(json.dumps({"grecall": 0.5, "sampled_with": {**made, "samples_per_graph": 1}}))
    (run / "sampling.json").write_text(json.dumps({"fingerprint": made}))
    record = {"source": str(run), "kind": "folder"}
    assert list(renders_of(record)) == ["g0_k0"]
    (run / "sampling.json").write_text(json.dumps({"fingerprint": {**made, "sampling": {"seed": 5}}}))
    refused = []
    assert renders_of(record, refused) == {}
    assert refused == [f"{run / 'renders'}: not shown: sampled again since the evaluation, with other settings "
                       f"(sampling.seed)"]


def test_a_tracker_run_is_never_given_the_numbers_of_a_redo_it_did_not_log(tmp_path):
    """A redo without MLflow (``seed=8 logger=none``) left ``mlflow_run.json`` naming the seed-7 run, and a load of
    the store gave that run seed 8's numbers; a relaunch continuing a wandb run wrote it offline into a second folder
    of the same id, read as two runs (its seed counted twice in a mean over seeds)."""
    import json
    from types import SimpleNamespace

    from spread.reporting.runs import latest_wandb_folders
    from spread.results.store import made_the_folder, run_record
    from spread.runtime.fingerprint import canonical

    run = tmp_path / "s"
    (run / "scenes").mkdir(parents=True)
    measured = {"ckpt_sha256": "ab", "guidance": {"mode": "none"}, "sampling": {"seed": 7}, "samples_per_graph": 1}
    (run / "mlflow_run.json").write_text(json.dumps({"run_id": "r7"}))
    (run / "metrics.json").write_text(json.dumps({"grecall": 0.18, "n_scenes": 3, "n_evaluated": 3,
                                                  "sampled_with": {**measured, "sampling": {"seed": 8}}}))
    assert not made_the_folder("r7", run, canonical(measured))  # the folder holds seed 8's numbers now
    assert made_the_folder("r7", run, canonical({**measured, "sampling": {"seed": 8}}))
    assert made_the_folder("r7", run) and not made_the_folder("r6", run)  # no tag: the run file decides, as before
    tags = {"spread.identity": canonical(measured), "spread.run_folder": str(run)}
    mlflow_run = SimpleNamespace(data=SimpleNamespace(tags=tags, metrics={"grecall": 0.24}, params={"seed": "7"}),
                                 info=SimpleNamespace(run_id="r7", run_name="s7", experiment_id="0", status="FINISHED"))
    record = run_record(mlflow_run, {"0": "e"})
    assert record["grecall"] == 0.24 and record["settings"]["seed"] == 7  # its own numbers, never the redo's

    wandb = [("wandb", tmp_path / "w" / f"offline-run-20261203_{t}-{i}")
             for t, i in (("142957", "a1"), ("143026", "b2"), ("143052", "a1"))]
    assert latest_wandb_folders([("folder", run), *wandb]) == [("folder", run), wandb[1], wandb[2]]
    for _, folder in wandb:  # as find_runs meets them in a folder of runs
        (folder / "files").mkdir(parents=True)
        (folder / "files" / "wandb-summary.json").write_text(json.dumps({"grecall": 0.5}))
    from spread.reporting.runs import find_runs

    assert find_runs([str(tmp_path / "w")])[0] == [wandb[1], wandb[2]]
