"""A command line that cannot run is refused in one line before anything is made (docs/robustness.md, round 9).

* Every Hydra console script composes its command line once before Hydra runs (``spread.cli.errors.compose_problem``):
  required settings left unset (``???``) are all named at once, where Hydra stopped at the first with a traceback
  from resolving the run folder; an override that names no key, no config group option, or does not parse is one
  line without Hydra's list of config sources. Hydra's own flags (``--cfg``) are left to Hydra; a multirun (``-m``)
  is expanded into its jobs as Hydra's basic sweeper expands it, each composed and its settings built, so a job that
  cannot run is refused by its number before the first job runs (``spread.cli.multirun``, round 13).
* ``trainer.*`` values are checked against Lightning's ``Trainer`` arguments before a launch records its config or
  opens a logger run (``spread.training.trainer_settings``): a relaunch with a value Lightning refuses leaves the run
  folder byte for byte as it was.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from helpers import FAST_TRAIN, SCRIPTS, SMALL_MODEL, compose, make_dataset, train_in_process, user_error
from spread.cli.errors import compose_problem
from spread.training.trainer_settings import trainer_setting_problem

CONF = Path(__file__).resolve().parents[1] / "conf"


@pytest.mark.parametrize("name, keys", [
    ("spread-train", "data.root"), ("spread-train-ray", "data.root"), ("spread-sample", "ckpt, data.root, out_dir"),
    ("spread-evaluate", "out_dir, reference, scenes"), ("spread-export", "out_dir, scenes"),
    ("spread-import", "out_dir, source, src"), ("spread-report", "runs"), ("spread-generate", "out_dir")])
def test_a_console_script_without_its_required_settings_names_them_all_in_one_line_and_makes_nothing(name, keys,
                                                                                                    tmp_path):
    line, _ = user_error(name, cwd=tmp_path)
    assert f"not given: {keys} (add " in line, line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("name", [pytest.param("spread-train", marks=pytest.mark.slow),  # also test_robustness's
                                  "spread-train-ray"])
def test_a_training_script_given_data_without_scenes_says_so_in_one_line_before_ray_or_the_folder(name, tmp_path):
    out, empty = tmp_path / "run", tmp_path / "rooms"
    empty.mkdir()
    line, proc = user_error(name, "experiment=quick", f"data.root={empty}", f"out_dir={out}", cwd=tmp_path)
    assert line == (f"{name}: data.root={empty}: no scene files in {empty / 'train'} to train on "
                    "(HYDRA_FULL_ERROR=1 shows the traceback)"), line
    assert "Ray" not in proc.stdout + proc.stderr  # the driver refused it: no worker raised it 2× in a traceback
    assert not (out / "config.yaml").exists()


@pytest.mark.parametrize("override, says", [
    ("model=nosuch", ["Could not find 'model/nosuch'", "Available options in 'model': ", " paper "]),
    ("trainer.nonexistent=3", ["Could not override 'trainer.nonexistent'", "Key 'nonexistent' is not in struct"]),
    ("seed=1,2", ["Ambiguous value for argument 'seed=1,2'", "add --multirun"]),
    ("data.root=[1,2", ["no viable alternative at input '[1,2'"]),
])
def test_an_override_that_does_not_compose_is_one_line_saying_what_is_wrong(override, says):
    problem = compose_problem("train", ["data.root=/d", override])
    assert problem is not None and "\n" not in problem and "Config search path" not in problem, problem
    for part in says:
        assert part in problem, problem


def test_a_command_line_that_composes_passes_and_hydra_flags_and_its_own_settings_are_left_to_hydra():
    assert compose_problem("train", ["experiment=quick", "data.root=/d", "trainer.max_steps=3"]) is None
    assert compose_problem("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o", "guidance=paper"]) is None
    assert compose_problem("train", ["--cfg", "job"]) is None  # prints the config, ??? and all
    assert compose_problem("train", ["-m", "seed=1,2", "data.root=/d"]) is None  # a sweep whose jobs compose
    assert compose_problem("train", ["data.root=/d", "hydra.run.dir=/x", "hydra/job_logging=disabled"]) is None
    assert compose_problem("train", ["hydra.searchpath=[file:///nowhere]", "model=nosuch"]) is None
    assert compose_problem("train", ["data.root=/d", "hydra.mode=MULTIRUN", "seed=0,1"]) is None  # a multirun too
    # values that resolve only inside the running app are not resolved here (a ${hydra:...} raised a traceback)
    assert compose_problem("sample", ["ckpt=/c", "data.root=/d", "out_dir=${hydra:runtime.cwd}/s"]) is None
    assert compose_problem("sample", ["+sweep=guidance_grid", "data.root=/d"]) == \
        "required setting not given: ckpt (add ckpt=...)"  # its out_dir interpolates the unset ckpt


def test_the_composed_config_is_still_printed_by_hydra_with_its_unset_settings(tmp_path):
    proc = subprocess.run([str(SCRIPTS / "spread-train"), "--cfg", "job"], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "root: ???" in proc.stdout and list(tmp_path.iterdir()) == []


def test_a_multirun_job_that_reads_an_unset_required_setting_ends_in_one_line(tmp_path):
    line, _ = user_error("spread-train", "-m", "seed=1,2", "logger=none", cwd=tmp_path)  # refused ahead
    assert line.startswith("spread-train: job #0 of the multirun (seed=1): required setting not given: data.root "
                           "(add data.root=..."), line
    line, _ = user_error("spread-train", "hydra.mode=MULTIRUN", "seed=1,2", "logger=none", cwd=tmp_path)  # by Hydra
    assert "required setting not given: data.root (add data.root=...)" in line, line


SAMPLE = ["ckpt=/c", "data.root=/d", "out_dir=/o"]


@pytest.mark.parametrize("sweep, says", [
    (["sampler.kind=ddim,nope"], "job #1 of the multirun (sampler.kind=nope): unknown sampler 'nope' (known: "),
    (["sampler.eta=0,2"], "job #1 of the multirun (sampler.eta=2): sampler.eta=2.0: expected a number in [0, 1]"),
    (["guidance.collision=1,abc"], "job #1 of the multirun (guidance.collision=abc): Error merging override "),
    (["sampler.kind=ddim,ddpm", "sampler.eta=0,0.5"],  # only the product's last job (ddpm at eta 0.5) is refused
     "job #3 of the multirun (sampler.kind=ddpm sampler.eta=0.5): sampler.eta=0.5: only the ddim sampler reads eta"),
])
def test_a_multirun_job_whose_settings_are_refused_is_named_by_its_number_before_any_job_runs(sweep, says):
    problem = compose_problem("sample", ["-m", *SAMPLE, *sweep])
    assert problem is not None and problem.startswith(says), problem


def test_a_multirun_job_whose_trainer_values_lightning_refuses_is_named_before_any_job_runs():
    problem = compose_problem("train", ["-m", "data.root=/d", "trainer.max_steps=3,abc"])
    assert problem == "job #1 of the multirun (trainer.max_steps=abc): trainer.max_steps='abc': Lightning's Trainer " \
                      "takes int here", problem
    assert compose_problem("train", ["-m", "data.root=/d", "trainer.max_steps=3,4", "seed=0,1"]) is None


def test_a_refused_multirun_job_stops_the_command_line_before_the_first_job_starts(tmp_path):
    # job #0 alone would fail on the missing checkpoint, after Hydra made its folders: refused ahead, nothing made
    line, proc = user_error("spread-sample", "-m", "ckpt=a.ckpt", "data.root=d", f"out_dir={tmp_path / 'o'}",
                            "sampler.eta=0,2", cwd=tmp_path)
    assert line.startswith("spread-sample: job #1 of the multirun (sampler.eta=2): sampler.eta=2.0: "), line
    assert "Launching" not in proc.stdout + proc.stderr and list(tmp_path.iterdir()) == []


def test_a_multirun_whose_jobs_share_one_out_dir_is_refused_before_the_first_job(tmp_path):
    """Jobs writing to one folder: the later one redid (deleting), refused or mixed with what the earlier wrote."""
    shared = compose_problem("sample", ["-m", *SAMPLE, "seed=0,1"])
    assert shared == ("jobs #0 and #1 of the multirun write to one out_dir=/o: the later job would redo, refuse or "
                      "delete what the earlier one wrote; give each job its own out_dir, one that names the swept keys "
                      "(e.g. 'out_dir=/o/${seed}')"), shared
    assert compose_problem("sample", ["-m", "ckpt=/c", "data.root=/d", "out_dir=/o/${seed}", "seed=0,1"]) is None
    assert compose_problem("sample", ["-m", "ckpt=/c", "data.root=/d", "out_dir=/o/${sampler.kind}", "seed=0,1",
                                      "sampler.kind=ddim,ddpm"]).endswith("(e.g. 'out_dir=/o/ddim/${seed}')")
    assert compose_problem("sample", ["-m", *SAMPLE, "seed=0,0"]) == \
        "job #1 of the multirun repeats job #0 (both write to out_dir=/o): give each setting once"
    assert compose_problem("train", ["-m", "data.root=/d", "seed=0,1"]) is None  # ${now:...}: each job's own time
    line, proc = user_error("spread-evaluate", "-m", "scenes=s", "reference=r", f"out_dir={tmp_path / 'e'}",
                            "seed=3,4", cwd=tmp_path)
    assert line.startswith(f"spread-evaluate: jobs #0 and #1 of the multirun write to one out_dir={tmp_path / 'e'}"), line
    assert list(tmp_path.iterdir()) == []


def test_a_multirun_is_expanded_into_the_jobs_hydras_basic_sweeper_runs_in_its_order():
    from spread.cli.multirun import sweep_jobs

    jobs = sweep_jobs("sample", ["-m", "+sweep=guidance_grid", "ckpt=/c", "data.root=/d", "guidance.relation=1e-3",
                                 "seed=0,1"])  # the config's grid, one key fixed on the command line, one swept
    assert len(jobs) == 3 * 3 * 1 * 2
    assert jobs[0] == ["guidance.collision=0.0", "guidance.gravity=0.0", "guidance.relation=0.001",
                       "+sweep=guidance_grid", "ckpt=/c", "data.root=/d", "seed=0"]
    assert jobs[1][-1] == "seed=1" and jobs[2][:2] == ["guidance.collision=0.0", "guidance.gravity=0.001"]
    assert compose_problem("sample", ["-m", "+sweep=guidance_grid", "ckpt=/c", "data.root=/d"]) is None  # README
    globbed = sweep_jobs("sample", ["-m", *SAMPLE, "sampler=glob(ddi*)", "seed=range(0,2)"])  # Hydra's other sweeps
    assert [job[-2:] for job in globbed] == [["sampler=ddim100", "seed=0"], ["sampler=ddim100", "seed=1"],
                                             ["sampler=ddim50", "seed=0"], ["sampler=ddim50", "seed=1"]], globbed
    # another sweeper chooses its jobs as it runs: left to it
    assert sweep_jobs("sample", ["-m", *SAMPLE, "seed=0,1", "hydra.sweeper._target_=my.Sweeper"]) is None


def test_a_grid_above_the_limit_is_checked_on_jobs_holding_every_swept_value_once():
    from spread.cli.multirun import ALL_JOBS_LIMIT, covering_jobs

    grid = [[f"a={a}", f"b={b}", f"c={c}"] for a in range(5) for b in range(5) for c in range(5)]
    cover = covering_jobs(grid)
    assert len(cover) == 1 + 4 * 3 and all(job in grid for job in cover)
    assert {o for job in cover for o in job} == {o for job in grid for o in job}
    assert len(grid) > ALL_JOBS_LIMIT  # a bad value anywhere in such a grid is still refused ahead:
    problem = compose_problem("sample", ["-m", *SAMPLE, "seed=0,1,2,3,4", "sampler.steps=1,2,3,4,5",
                                         "guidance.collision=0,1,2,3,abc"])
    assert problem.startswith("job #4 of the multirun (seed=0 sampler.steps=1 guidance.collision=abc): "), problem


TRAINER = {"_target_": "lightning.pytorch.Trainer"}


def test_trainer_values_are_checked_against_the_arguments_lightnings_trainer_takes():
    assert trainer_setting_problem({**TRAINER, "max_steps": 10, "max_epochs": None, "precision": "bf16-mixed",
                                    "devices": "auto", "limit_val_batches": 0.5, "deterministic": "warn",
                                    "max_time": "00:01:00:00", "accelerator": "cpu"}) is None
    assert trainer_setting_problem({**TRAINER, "max_steps": "abc"}) == \
        "trainer.max_steps='abc': Lightning's Trainer takes int here"
    assert trainer_setting_problem({**TRAINER, "max_steps": 1000.0}) == \
        "trainer.max_steps=1000.0: Lightning's Trainer takes int here"
    assert trainer_setting_problem({**TRAINER, "max_steps": True}) is not None  # a bool is no count
    assert trainer_setting_problem({**TRAINER, "max_epochs": "x"}) == \
        "trainer.max_epochs='x': Lightning's Trainer takes one of int, None here"
    assert trainer_setting_problem({**TRAINER, "max_stepz": 5}) == \
        "trainer.max_stepz: Lightning's Trainer takes no such argument"
    precision = trainer_setting_problem({**TRAINER, "precision": "bf17"})
    assert precision.startswith("trainer.precision='bf17': Lightning's Trainer takes one of ") and \
        "'bf16-mixed'" in precision
    both = trainer_setting_problem({**TRAINER, "max_steps": "abc", "max_stepz": 5})
    assert both.count("; ") == 1 and "max_steps" in both and "max_stepz" in both
    # a launcher's own arguments (Ray Train's strategy, plugins) and another trainer class are not judged here
    assert trainer_setting_problem({**TRAINER, "strategy": 3}, {"strategy": object()}) is None
    assert trainer_setting_problem({"_target_": "my.Trainer", "max_steps": "abc"}) is None


@pytest.mark.parametrize("config", [f"trainer={p.stem}" for p in sorted((CONF / "trainer").glob("*.yaml"))]
                         + [f"experiment={p.stem}" for p in sorted((CONF / "experiment").glob("*.yaml"))])
def test_every_trainer_config_and_experiment_composes_to_values_lightnings_trainer_takes(config):
    from spread.training.trainer_settings import check_training_settings

    cfg = compose("train", "data.root=/d", config)
    assert trainer_setting_problem(cfg.trainer) is None
    check_training_settings(cfg)  # seed, threads, renders, the checkpoint's and callbacks' arguments


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> tuple[Path, Path]:
    """A dataset and a base model's run folder after 2 training steps."""
    dataset = make_dataset(tmp_path_factory.mktemp("cl_data"))
    out = tmp_path_factory.mktemp("cl_run") / "run"
    train_in_process(out, "experiment=quick", "model.variant=base", f"data.root={dataset}", "trainer.max_time=null",
                     "trainer.max_steps=2", *SMALL_MODEL, *FAST_TRAIN)
    return dataset, out


@pytest.mark.parametrize("override, says", [
    ("trainer.max_steps=4.5", "trainer.max_steps=4.5: Lightning's Trainer takes int here"),
    pytest.param("checkpoint.every_n_train_steps=-5", "checkpoint: MisconfigurationException: Invalid value for "
                 "every_n_train_steps=-5", marks=pytest.mark.slow),  # make test-slow: these three, 7 s each
    # each of these trained: a checkpoint at step 3 only (3 % 1.5 == 0), one render scene for 1.5
    pytest.param("checkpoint.every_n_train_steps=1.5",
                 "checkpoint.every_n_train_steps=1.5: ModelCheckpoint takes one of int", marks=pytest.mark.slow),
    pytest.param("renders.scenes=1.5", "renders.scenes=1.5: expected a whole number ≥ 1", marks=pytest.mark.slow),
    ("trainer.max_steps=1", "ckpt_path=")])  # …: the checkpoint is at step 2, past trainer.max_steps=1 (it recorded 1)
def test_a_relaunch_with_a_trainer_value_lightning_refuses_is_refused_by_name_and_leaves_the_run_folder_as_it_was(
        run, tmp_path, override, says):
    dataset, made = run
    folder = tmp_path / "run"
    shutil.copytree(made, folder)
    before = recorded(folder)
    line, _ = user_error("spread-train", "experiment=quick", "model.variant=base", f"data.root={dataset}",
                         "trainer.max_time=null", *SMALL_MODEL, *FAST_TRAIN, f"out_dir={folder}", "ckpt_path=last",
                         override)
    assert line.startswith(f"spread-train: {says}"), line
    if override == "trainer.max_steps=1":
        assert "the checkpoint is at step 2, past trainer.max_steps=1" in line, line
    assert recorded(folder) == before


def test_checkpoint_callback_and_render_values_their_classes_refuse_are_named_by_key_in_the_library_too():
    import hydra

    from spread.training.trainer_settings import built, check_renders, target_setting_problem

    cfg = compose("train", "data.root=/d", "checkpoint.every_n_train_steps=1.5")
    assert target_setting_problem(cfg.checkpoint, "checkpoint").startswith(
        "checkpoint.every_n_train_steps=1.5: ModelCheckpoint takes one of int")
    assert target_setting_problem(compose("train", "data.root=/d").checkpoint, "checkpoint") is None
    with pytest.raises(ValueError, match=r"^checkpoint: MisconfigurationException: .*every_n_train_steps=-5"):
        built(lambda: hydra.utils.instantiate(compose("train", "data.root=/d",
                                                      "checkpoint.every_n_train_steps=-5").checkpoint), "checkpoint")
    with pytest.raises(ValueError, match=r"^renders.scenes=1.5: expected a whole number ≥ 1"):
        check_renders({"every_n_epochs": 1, "scenes": 1.5, "seed": 0})
    check_renders({"every_n_epochs": 0, "scenes": 2, "seed": 0})


def recorded(folder: Path) -> dict:
    """A run folder's files with their bytes, but the folder's lock (which names the last launch) and Hydra's log of
    the command (which Hydra opens before any check can run)."""
    return {p: p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".spread.lock" and p.suffix != ".log"}


def test_spread_sweep_names_every_unset_setting_and_refuses_a_checkpoint_or_data_that_is_not_there_before_ray(
        tmp_path):
    out = tmp_path / "sweep"
    line, _ = user_error("spread-sweep", f"out_dir={out}", cwd=tmp_path)
    assert line.startswith("spread-sweep: required settings not given: ckpt, data.root (add ckpt=... data.root=..."), line
    store = tmp_path / "store" / "mlflow.db"
    line, proc = user_error("spread-sweep", f"out_dir={out}", f"ckpt={tmp_path / 'no.ckpt'}", f"data.root={tmp_path}",
                            "logger=mlflow", f"logger.tracking_uri={store}", cwd=tmp_path)
    assert line == f"spread-sweep: {tmp_path / 'no.ckpt'}: no such checkpoint file", line
    assert "Ray" not in proc.stderr + proc.stdout  # refused before Ray started: no trial, no table
    assert not store.exists()  # ... and before the sweep's parent run opened (it was left FAILED in the store)
    line, _ = user_error("spread-sweep", "command=train", f"out_dir={out}", f"data.root={tmp_path / 'none'}",
                         "seed=1,2", cwd=tmp_path)
    assert line == f"spread-sweep: data.root={tmp_path / 'none'}: no scene files in {tmp_path / 'none' / 'train'} to train on", line
    assert not out.exists()


@pytest.mark.parametrize("name", ["spread-dashboard", "spread-release-ckpt"])
def test_help_prints_the_usage_of_a_console_script_that_takes_key_value_arguments(name):
    proc = subprocess.run([str(SCRIPTS / name), "--help"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout.startswith(f"``{name} "), proc.stdout[:300] + proc.stderr[-1000:]


@pytest.mark.parametrize("command, base, override, says", [
    ("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o"], "workers=-2", "workers=-2: expected a whole number ≥ 0"),
    ("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o"], "renders=-1", "renders=-1: expected a whole number ≥ 0"),
    ("evaluate", ["scenes=/s", "reference=/r", "out_dir=/o"], "chunk_size=0",
     "chunk_size=0: expected a whole number ≥ 1"),
    ("evaluate", ["scenes=/s", "reference=/r", "out_dir=/o"], "bootstrap_resamples=-5",
     "bootstrap_resamples=-5: expected a whole number ≥ 0"),
    # each of these sampled nothing usable after the finished folder was cleared (NaN poses; a traceback)
    ("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o"], "sampler.eta=nan", r"sampler.eta=nan: expected a number in \[0, 1\]"),
    ("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o", "sampler=ddim50"], "sampler.eta=2", r"sampler.eta=2.0: expected"),
    ("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o"], "threads=-2", "threads=-2: expected a whole number ≥ 1, or null"),
    ("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o"], "seed=-1", "seed=-1 .*: expected a whole number ≥ 0"),
    ("evaluate", ["scenes=/s", "reference=/r", "out_dir=/o"], "seed=-1", "seed=-1 .*: expected a whole number ≥ 0"),
    # refused when spread-sample starts, not after the sampling ran
    ("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o", "evaluate=true"], "evaluation.chunk_size=0",
     "evaluation.chunk_size=0: expected a whole number ≥ 1"),
])
def test_a_count_below_its_least_is_refused_by_key_not_taken_for_another_value(command, base, override, says):
    """``workers=-2`` sampled in this process and ``chunk_size=0`` evaluated one scene a task, each recorded as given."""
    from spread.configs import to_object

    with pytest.raises(ValueError, match=says):
        to_object(compose(command, *base, override))
    to_object(compose(command, *base))  # the defaults pass


@pytest.mark.parametrize("override, says", [
    ("seed=-1", "seed=-1: expected a whole number in [0, 2**32)"),
    ("threads=0", "threads=0: expected a whole number ≥ 1, or null for torch's default")])
def test_a_training_seed_or_thread_count_lightning_or_torch_refuses_is_refused_by_key(override, says):
    from spread.training.trainer_settings import check_training_settings

    with pytest.raises(ValueError) as refused:
        check_training_settings(compose("train", "data.root=/d", override))
    assert str(refused.value) == says
    check_training_settings(compose("train", "data.root=/d"))


@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_a_redo_removes_only_the_pictures_its_own_runs_made_in_renders(run, tmp_path):
    """A relaunch with other settings deleted every ``.png`` of ``renders/`` (a dataset's overview, a user's picture);
    it removes the sampling's own (named after its scenes, or listed in ``sampling.json``) and the evaluation's
    (named after the scenes its ``per_scene.jsonl`` measured), and nothing else."""
    from helpers import sample_in_process
    from spread.configs import to_object
    from spread.evaluation import run_evaluation

    dataset, made = run
    ckpt = made / "checkpoints" / "last.ckpt"
    out = tmp_path / "s"
    sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "logger=none", "renders=2")
    own = sorted(p.name for p in (out / "renders").glob("*.png"))
    assert len(own) == 2
    (out / "renders" / "overview.png").write_bytes(b"a user's picture")
    again = sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={out}", "logger=none", "renders=1",
                              "seed=1")
    assert again.manifest["redone_because"] and again.manifest["written_this_run"] > 0
    assert (out / "renders" / "overview.png").read_bytes() == b"a user's picture"
    assert sorted(p.name for p in (out / "renders").glob("*.png")) == sorted([own[0], "overview.png"])

    evaluated = tmp_path / "e"

    def evaluate(*overrides):
        return run_evaluation(to_object(compose(
            "evaluate", f"scenes={out / 'scenes'}", f"reference={dataset}", f"out_dir={evaluated}", "progress=false",
            "ray.num_cpus=1", "fid.enabled=false", "protocol.stability_runs=1", "protocol.stability_steps=20",
            "protocol.metrics=[col_mesh]", *overrides)))

    evaluate("renders=2")
    mine = sorted(p.name for p in (evaluated / "renders").glob("*.png"))
    assert len(mine) >= 1
    (evaluated / "renders" / "overview.png").write_bytes(b"a user's picture")
    evaluate("renders=0", "protocol.collision_threshold=0.02")  # another protocol: redone
    assert sorted(p.name for p in (evaluated / "renders").glob("*.png")) == ["overview.png"]


def test_a_hand_damaged_metrics_json_is_refused_by_file_and_key_and_an_inverted_interval_is_no_interval(tmp_path):
    import json

    from spread.reporting.runs import RunError, read_run_folder
    from spread.reporting.tables import Column

    for key, value, says in [("bootstrap", "x", "key 'bootstrap' is str, expected an object"),
                             ("per_room_type", {"bedroom": 5}, "key 'per_room_type' is not an object of room types"),
                             ("n_scenes", "12", r"key 'n_scenes' is '12', expected a whole number in \[0, 2\^53\)"),
                             ("n_failed", -1.5, "key 'n_failed' is -1.5, expected a whole number in"),  # printed as is
                             ("n_scenes", 10 ** 400, "key 'n_scenes' is 1000000000000000000000000000000000000000, "
                                                     "expected a whole number in"),  # a traceback from float()
                             # the bootstrap block's fields and sampled_with: tracebacks or nameless errors before
                             ("bootstrap", {"resamples": 100, "seed": 0}, "key 'bootstrap.level' is missing"),
                             ("bootstrap", {"level": 0.95, "resamples": "1000"},
                              "key 'bootstrap.resamples' is '1000', expected a whole number ≥ 0"),
                             ("bootstrap", {"level": 0.95, "seed": [1, 2]}, r"key 'bootstrap.seed' is \[1, 2\]"),
                             ("bootstrap", {"level": 0.95, "measured": {"asd": "3"}},
                              "key 'bootstrap.measured' is not an object of whole counts"),
                             ("bootstrap", {"level": 95}, "key 'bootstrap.level' is 95, expected a number in"),
                             ("sampled_with", {"sampling": "x", "guidance": "refine"},
                              "key 'sampled_with' is not a sampling identity"),
                             # a NaN showed as –, the missing value, in every table
                             ("col_mesh", float("nan"), "key 'col_mesh' is NaN, a value spread-evaluate never writes"),
                             ("asd_hi", float("nan"), "key 'asd_hi' is NaN"),
                             ("per_room_type", {"bedroom": {"stability": float("nan")}},
                              "key 'per_room_type.bedroom.stability' is NaN")]:
        folder = tmp_path / f"{key}{len(list(tmp_path.iterdir()))}"
        folder.mkdir()
        (folder / "metrics.json").write_text(json.dumps({"grecall": 0.5, "n_evaluated": 3, key: value}))
        with pytest.raises(RunError, match=f"{folder / 'metrics.json'}: {says}"):
            read_run_folder(folder)
    line, _ = user_error("spread-report", f"runs=[{folder}]", f"out_dir={tmp_path / 'report'}")
    assert line.startswith(f"spread-report: {folder / 'metrics.json'}: key 'per_room_type.bedroom.stability' is NaN"), line
    deep = tmp_path / "deep"
    deep.mkdir()
    (deep / "metrics.json").write_text("[" * 100_000 + "]" * 100_000)  # past Python's parser: a RecursionError
    with pytest.raises(RunError, match=f"{deep / 'metrics.json'}: not valid JSON \\(nested deeper than"):
        read_run_folder(deep)
    asd = Column("asd", "ASD (mm)", digits=1, scale=1000.0)  # 1e307 m is finite; in mm it is not: never "inf"
    assert asd.valid(1e307) is None and asd.format(1e307) == "invalid (1e+307)" and asd.format(0.0146) == "14.6"
    column = Column("grecall", "GRecall", digits=3)
    assert column.half_width({"grecall": 0.5, "grecall_lo": 0.4, "grecall_hi": 0.6}) == pytest.approx(0.1)
    assert column.half_width({"grecall": 0.5, "grecall_lo": 0.9, "grecall_hi": 0.1}) is None  # was "± -0.400"
    assert column.cell({"grecall": 0.5, "grecall_lo": 0.9, "grecall_hi": 0.1}) == "0.500"


def test_spread_ablate_and_compare_refuse_a_split_the_data_folder_does_not_have_before_any_stage(run, tmp_path):
    dataset, _ = run
    for name, preset in (("spread-ablate", "+preset=quick"), ("spread-compare", "+table1=quick")):
        out = tmp_path / name
        line, _ = user_error(name, preset, "logger=none", f"data.root={dataset}", f"out_dir={out}", "data.split=bogus")
        assert line.startswith(f"{name}: data.root={dataset}: no 'bogus' split folder (data.split=bogus)"), line
        assert not out.exists() or list(out.iterdir()) == []  # no record, no stage, no empty log of Hydra's


def test_a_command_refuses_an_out_dir_that_holds_a_dataset_or_another_commands_run(run, tmp_path):
    """An evaluation wrote over a training run's ``metrics.json``; a training run replaced a sampling run's recorded
    config; a sampling run wrote its scenes into the dataset folder. The evaluation of a sampling run's own scenes in
    its folder (``spread-sample evaluate=true``, ``spread-evaluate scenes=<run>/scenes out_dir=<run>``) stays."""
    from helpers import sample_in_process
    from spread.io import check_folder_kind, folder_kinds

    dataset, made = run
    assert set(folder_kinds(made)) == {"training run"} and set(folder_kinds(dataset)) == {"dataset"}
    with pytest.raises(ValueError, match=f"out_dir={made}: holds a training run .*; spread-evaluate would write over"):
        check_folder_kind(made, "spread-evaluate", {"evaluation"})
    check_folder_kind(made, "spread-train", {"training run"})  # its own kind
    check_folder_kind(tmp_path / "new", "spread-train", {"training run"})  # nothing there yet
    ckpt = made / "checkpoints" / "last.ckpt"
    line, _ = user_error("spread-sample", f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={dataset}",
                         "logger=none", "workers=0")
    assert line.startswith(f"spread-sample: out_dir={dataset}: holds a dataset ({dataset / 'assets' / 'index.json'})")
    assert not (dataset / "scenes").exists()
    sampled = tmp_path / "s"
    sample_in_process(f"ckpt={ckpt}", f"data.root={dataset}", f"out_dir={sampled}", "logger=none")
    before = recorded(sampled)
    line, _ = user_error("spread-train", "experiment=quick", "model.variant=base", f"data.root={dataset}",
                         *SMALL_MODEL, *FAST_TRAIN, f"out_dir={sampled}", "trainer.max_steps=1")
    assert line.startswith(f"spread-train: out_dir={sampled}: holds a sampling run ({sampled / 'sampling.json'})"), line
    assert recorded(sampled) == before
