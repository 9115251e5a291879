"""Hostile inputs, round 17 (docs/robustness.md): `spread-train` resumes only what it can continue as it was trained,
and refuses values Lightning or the optimiser take only to fail late (or never)."""

from __future__ import annotations

import hashlib
import math
import re

import pytest
import torch

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset, train_in_process, user_error

COMMON = ["experiment=quick", *SMALL_MODEL, *FAST_TRAIN, "trainer.limit_val_batches=0", "logger=none"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("r17") / "d")


def test_a_resume_with_another_precision_or_other_batches_an_epoch_is_refused_by_key(data, tmp_path):
    """Steps 1–2 in 32-true resumed in bf16-mixed were recorded as bf16-mixed; a resume taking 1 batch an epoch
    where the run took all of them changed where in the data it stood. Both are refused, naming the change."""
    out = tmp_path / "run"
    args = [f"data.root={data}", *COMMON, "trainer.max_time=null"]
    train_in_process(out, *args, "trainer.max_steps=2")
    with pytest.raises(ValueError, match=r"trainer\.precision: '32-true' -> 'bf16-mixed'"):
        train_in_process(out, *args, "trainer.max_steps=4", "ckpt_path=last", "trainer.precision=bf16-mixed")
    with pytest.raises(ValueError, match=r"trainer\.limit_train_batches: 'all' -> '1 batch'"):
        train_in_process(out, *args, "trainer.max_steps=4", "ckpt_path=last", "+trainer.limit_train_batches=1")
    # the same settings spelled otherwise are the same: 32 is Lightning's 32-true, 1.0 all the batches
    summary = train_in_process(out, *args, "trainer.max_steps=3", "ckpt_path=last", "trainer.precision=32",
                               "+trainer.limit_train_batches=1.0")
    assert summary["global_step"] == 3


def test_the_resume_of_a_run_that_used_its_time_limit_says_it_trains_nothing_and_a_longer_limit_trains_on(
        data, tmp_path, capsys):
    """Lightning's Timer counts the time of every launch: the resume of a run that used its ``trainer.max_time``
    (the README's ``ckpt_path=last`` line after ``experiment=quick``'s 4 minutes) trained no step and printed only
    success. It still trains nothing — the run is done, as one at its ``max_steps`` is, so a study's or the demo's
    relaunch goes on — but says so, with the way on; a longer limit trains on."""
    out = tmp_path / "run"
    args = [f"data.root={data}", *COMMON, "trainer.max_steps=100000"]
    first = train_in_process(out, *args, "trainer.max_time=00:00:00:01")
    saved = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")
    assert saved["callbacks"]["Timer"]["time_elapsed"]["train"] >= 1.0
    capsys.readouterr()
    again = train_in_process(out, *args, "trainer.max_time=00:00:00:01", "ckpt_path=last")
    assert again["global_step"] == first["global_step"]
    said = capsys.readouterr().out
    assert re.search(r"spread-train: .*last\.ckpt has trained for \d+ s, its trainer\.max_time of 1 s .*: nothing to "
                     r"train; give a longer trainer\.max_time, or null, to train on", said), said
    longer = train_in_process(out, *args, "trainer.max_time=00:00:00:03", "ckpt_path=last")
    assert longer["global_step"] > first["global_step"]
    assert "nothing to train" not in capsys.readouterr().out


REFUSED = [
    ("trainer.max_time=abc", "trainer.max_time='abc': expected DD:HH:MM:SS"),
    ("trainer.max_time=00:04:00", "trainer.max_time='00:04:00': expected DD:HH:MM:SS"),
    ("trainer.max_epochs=-5", "trainer.max_epochs=-5: expected a whole number ≥ -1"),
    ("trainer.devices=0", "trainer.devices=0: expected a whole number ≥ 1 or -1"),
    ("trainer.limit_val_batches=-1", "trainer.limit_val_batches=-1: expected a share of the batches in [0.0, 1.0]"),
    ("trainer.limit_val_batches=1.5", "trainer.limit_val_batches=1.5: expected a share of the batches in [0.0, 1.0]"),
    ("trainer.accumulate_grad_batches=0", "trainer.accumulate_grad_batches=0: expected a whole number ≥ 1"),
    ("trainer.check_val_every_n_epoch=0", "trainer.check_val_every_n_epoch=0: expected a whole number ≥ 1"),
    ("trainer.gradient_clip_val=nan", "trainer.gradient_clip_val=nan: expected a finite number ≥ 0"),
    ("trainer.gradient_clip_val=-1", "trainer.gradient_clip_val=-1: expected a finite number ≥ 0"),
    ("model.lr=inf", "model.lr=inf: expected a finite number > 0"),
    ("model.lr=-1", "model.lr=-1.0: expected a finite number > 0"),
    ("model.weight_decay=inf", "model.weight_decay=inf: expected a finite number >= 0"),
    ("model.graph_dropout=1.5", "model.graph_dropout=1.5: expected a share in [0, 1]"),
    ("model.lr_final_ratio=nan", "model.lr_final_ratio=nan: expected a share of model.lr in [0, 1]"),
    ("model.lr_warmup_steps=-3", "model.lr_warmup_steps=-3: expected a whole number ≥ 0"),
    ("model.penetration_weight=inf", "model.penetration_weight must be a finite number >= 0, got inf"),
    ("fresh=no", "fresh='no': expected true or false"),
    ('checkpoint.filename="../../esc/s{step}"', "checkpoint.filename='../../esc/s{step}': a checkpoint's name within"),
]


@pytest.mark.parametrize("setting, said", REFUSED)
def test_values_that_fail_late_or_never_are_refused_by_key_before_the_trainer_or_the_model_is_built(data, setting,
                                                                                                      said):
    """Each was taken: ``max_time=abc`` failed in Lightning after the run's ``.hydra/config.yaml`` was rewritten;
    ``accumulate_grad_batches=0`` mid-fit (ZeroDivisionError); ``gradient_clip_val=nan`` at the first step;
    ``model.lr=inf`` trained to NaN weights and exited 0; ``fresh=no`` moved the run aside (a non-empty text is
    true); the checkpoint name wrote checkpoints outside the run."""
    import hydra

    from spread.training.trainer_settings import check_training_settings

    from helpers import compose

    cfg = compose("train", f"data.root={data}", *COMMON, setting)
    with pytest.raises(Exception) as refused:
        check_training_settings(cfg)
        hydra.utils.instantiate(cfg.model)
    cause = refused.value.__cause__ or refused.value
    assert isinstance(cause, ValueError) and said in str(cause), str(cause)


@pytest.mark.parametrize("setting", ["trainer.max_time=abc"])  # the others take the same path (above)
def test_spread_train_refuses_them_in_one_line_and_a_run_it_was_to_resume_keeps_its_record(data, tmp_path, setting):
    """The command line as typed: one line naming the key, and the run's ``.hydra/config.yaml`` as it was (rewritten
    before Lightning refused ``max_time=abc``)."""
    out = tmp_path / "run"
    (out / ".hydra").mkdir(parents=True)
    record = out / ".hydra" / "config.yaml"
    record.write_text("out_dir: the earlier run's record\n")
    line, _ = user_error("spread-train", f"data.root={data}", f"out_dir={out}", *COMMON, "trainer.max_steps=2",
                         setting)
    said = dict(REFUSED)[setting]
    assert line.startswith(f"spread-train: {said}"), line
    assert record.read_text() == "out_dir: the earlier run's record\n"
    assert sorted(p.name for p in out.iterdir()) == [".hydra"] and not (tmp_path / "esc").exists()


def test_fresh_with_a_resume_of_the_same_run_is_refused_as_the_two_contradict(data, tmp_path):
    """``fresh=true ckpt_path=last`` resumed the run with no word of ``fresh``."""
    out = tmp_path / "run"
    args = [f"data.root={data}", *COMMON, "trainer.max_time=null"]
    train_in_process(out, *args, "trainer.max_steps=1")
    before = hashlib.sha256((out / "checkpoints" / "last.ckpt").read_bytes()).hexdigest()
    with pytest.raises(ValueError, match=r"^fresh=true with ckpt_path=last: fresh starts .* over .* give one of the "
                                         r"two$"):
        train_in_process(out, *args, "trainer.max_steps=2", "ckpt_path=last", "fresh=true")
    assert hashlib.sha256((out / "checkpoints" / "last.ckpt").read_bytes()).hexdigest() == before
    assert not (out / "previous").exists()


def test_a_training_summary_writes_null_for_a_value_that_is_not_finite_never_invalid_json(tmp_path):
    """``metrics.json`` held ``NaN`` and ``Infinity`` (``train/loss``, ``lr-AdamW``), which no JSON reader takes."""
    import json
    from types import SimpleNamespace

    from spread.training.fit import write_summary

    trainer = SimpleNamespace(global_step=3, current_epoch=1, is_global_zero=True, world_size=1, callback_metrics={
        "train/loss": torch.tensor(math.nan), "lr-AdamW": torch.tensor(math.inf), "val/loss": torch.tensor(0.5)})
    write_summary(trainer, tmp_path, None)
    text = (tmp_path / "metrics.json").read_text()
    assert json.loads(text, parse_constant=lambda c: pytest.fail(f"metrics.json holds {c}"))["metrics"] == {
        "train/loss": None, "lr-AdamW": None, "val/loss": 0.5}


@pytest.mark.parametrize("command", ["spread-generate", "spread-train"])
def test_an_empty_out_dir_is_refused_before_anything_is_written(tmp_path, command):
    """``out_dir=`` wrote the run into the working folder and Hydra's record of it to ``/logs/<command>/<time>``, at
    the top of the file system."""
    import os

    before = os.path.exists("/logs")
    line, _ = user_error(command, "out_dir=", "rooms=2" if command == "spread-generate" else "experiment=quick",
                         cwd=tmp_path)
    assert line == f"{command}: out_dir= is empty; give a folder (out_dir=. for the working folder)"
    assert list(tmp_path.iterdir()) == [] and os.path.exists("/logs") == before


def test_an_unknown_render_sampler_is_refused_before_training_not_at_the_first_render_epoch(data):
    """``renders.sampler=bogus-7`` failed after ``renders.every_n_epochs`` epochs of training (its MLflow run FAILED,
    the steps since the last checkpoint lost)."""
    from spread.training.trainer_settings import check_training_settings

    from helpers import compose

    with pytest.raises(ValueError, match=r"^renders\.sampler='bogus-7': unknown sampler 'bogus'"):
        check_training_settings(compose("train", f"data.root={data}", *COMMON, "renders.sampler=bogus-7"))
    check_training_settings(compose("train", f"data.root={data}", *COMMON, "renders.sampler=ddim-5"))


@pytest.mark.parametrize("missing", ["stats.json", "assets/index.json"])
def test_a_dataset_without_its_statistics_or_asset_index_is_refused_before_the_run_is_recorded(data, tmp_path,
                                                                                                missing):
    """Each failed when the data was set up, after the run's config and log were written."""
    import shutil

    from spread.data.splits import fit_problem

    copy = tmp_path / "d"
    shutil.copytree(data, copy)
    assert fit_problem(copy, True) is None
    (copy / missing).unlink()
    what = "the normalisation bounds" if missing == "stats.json" else "the asset library"
    assert fit_problem(copy, True) == (f"data.root={copy}: no {missing} ({what}, which spread-generate and "
                                       f"spread-import write); give a whole dataset folder")


def test_hydra_run_dir_on_the_command_line_is_refused_as_out_dir_is_the_run_folder(tmp_path):
    """``out_dir=A hydra.run.dir=B`` trained into B, whose record said ``out_dir: A``: a relaunch with ``out_dir=A
    ckpt_path=last`` found no run, and refusals named out_dir for what B held."""
    line, _ = user_error("spread-train", f"out_dir={tmp_path / 'A'}", f"hydra.run.dir={tmp_path / 'B'}",
                         "experiment=quick", cwd=tmp_path)
    assert line == (f"spread-train: hydra.run.dir={tmp_path / 'B'}: Hydra's run folder follows out_dir (conf/hydra); "
                    f"give out_dir=<folder> instead")
    assert list(tmp_path.iterdir()) == []


def test_a_file_that_is_no_checkpoint_or_npz_is_named_for_what_it_is_not_called_pickled_code(tmp_path):
    """``ckpt_path=<a dataset's stats.json>`` was refused as holding "pickled Python objects … which could run code",
    and a scene file of other bytes as "pickled (object) data": numpy and torch read any bytes that are not a zip as a
    pickle. A real pickle is still refused as one."""
    import pickle

    from spread.safe_load import UnsafeFileError, load_checkpoint, load_npz

    text, empty, code = tmp_path / "stats.json", tmp_path / "e.ckpt", tmp_path / "p.ckpt"
    text.write_text('{"bounds_translations": [0, 1]}')
    empty.write_bytes(b"")
    code.write_bytes(pickle.dumps({"a": pytest.raises}))  # a function: beyond plain data
    with pytest.raises(UnsafeFileError, match=r"stats\.json: not a readable checkpoint \(neither torch's zip format "
                                              r"nor its legacy one\): a text file starting with '\{\"bounds_transla'$"):
        load_checkpoint(text)
    with pytest.raises(UnsafeFileError, match=r"e\.ckpt: not a readable checkpoint .*: an empty file$"):
        load_checkpoint(empty)
    with pytest.raises(UnsafeFileError, match=r"stats\.json: not a readable \.npz archive \(a zip of \.npy arrays\): "
                                              r"a text file starting with"):
        load_npz(text)
    with pytest.raises(UnsafeFileError, match=r"p\.ckpt: refused — it holds pickled Python objects"):
        load_checkpoint(code)
