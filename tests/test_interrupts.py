"""Ctrl-C: ``spread-train`` stops after the step in progress, saves it as ``last.ckpt`` and exits 130 in one line
(Lightning saved nothing and exited 1); a study (ablation, comparison) stops with it instead of starting its next
stage, which it did when the training's exit looked like a failed stage."""

from __future__ import annotations

import os
import signal
import subprocess
import time

import pytest
import torch

from helpers import FAST_TRAIN, SCRIPTS, SMALL_MODEL, compose, make_dataset


def test_ctrl_c_stops_spread_train_after_its_step_saves_it_and_a_relaunch_goes_on(tmp_path):
    data = make_dataset(tmp_path / "d")
    out = tmp_path / "run"
    args = [str(SCRIPTS / "spread-train"), "experiment=quick", f"data.root={data}", f"out_dir={out}", *SMALL_MODEL,
            *FAST_TRAIN, "trainer.max_steps=100000", "trainer.max_time=null", "trainer.log_every_n_steps=1",
            "checkpoint.every_n_train_steps=100000", "trainer.limit_val_batches=0"]
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "SPREAD_DEBUG")}
    proc = subprocess.Popen(args, env={**env, "WANDB_MODE": "disabled"}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while not list(out.glob("csv/version_*/metrics.csv")) or \
                len(next(out.glob("csv/version_*/metrics.csv")).read_text().splitlines()) < 4:
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1][-3000:]
            time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr[-3000:]
    assert "Traceback" not in stderr and stderr.strip().splitlines()[-1] == "spread-train: interrupted (Ctrl-C)"
    assert "stopping after this step and saving its checkpoint" in stderr
    saved = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")["global_step"]
    assert saved >= 3 and f"interrupted at step {saved}:" in stdout  # the steps made are kept (none were)
    assert not (out / "metrics.json").exists()  # not a finished run: a study does not take it for one
    from helpers import train_in_process

    again = train_in_process(out, "experiment=quick", f"data.root={data}", *SMALL_MODEL, *FAST_TRAIN,
                             f"trainer.max_steps={saved + 2}", "trainer.max_time=null", "trainer.limit_val_batches=0",
                             "ckpt_path=last")
    assert again["global_step"] == saved + 2 and again["resumed_from"] == str(out / "checkpoints" / "last.ckpt")


def test_a_study_stops_at_a_training_stage_interrupted_by_ctrl_c(tmp_path):
    """In a study's process the training stage raises KeyboardInterrupt, which ``StageEngine.attempt`` lets through
    (a stage that raised anything else is recorded as failed and the next one starts), with the steps saved."""
    from lightning.pytorch.callbacks import Callback

    from spread.experiments.stages import StageEngine
    from spread.training.fit import train

    class CtrlC(Callback):  # the user presses Ctrl-C during step 2
        def on_train_batch_end(self, trainer, *args):
            if trainer.global_step == 2:
                os.kill(os.getpid(), signal.SIGINT)

    data = make_dataset(tmp_path / "d")
    out = tmp_path / "run"
    cfg = compose("train", "experiment=quick", f"data.root={data}", f"out_dir={out}", *SMALL_MODEL, *FAST_TRAIN,
                  "trainer.max_steps=50", "trainer.max_time=null", "trainer.limit_val_batches=0", "logger=none")
    engine = StageEngine.__new__(StageEngine)
    engine.status, engine.errors, engine.slot = {}, {}, None

    def stage():
        train(cfg, run_dir=out, extra_callbacks=[CtrlC()])

    with pytest.raises(KeyboardInterrupt):
        engine.attempt("train/base", stage, [])
    assert engine.status == {} and engine.errors == {}  # not recorded as a failed stage
    assert torch.load(out / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")["global_step"] == 2


def test_a_resume_with_another_accumulation_is_refused_and_an_accumulated_run_trains_every_step(tmp_path):
    """How many batches a step takes decides where in the data a resumed run stands: a checkpoint records it and a
    resume with another is refused (it was resumed, and with 3 training stalled on one batch, exit 0)."""
    from spread.training.fit import TRAINER_SETTINGS

    from helpers import train_in_process

    data = make_dataset(tmp_path / "d")
    out = tmp_path / "run"
    common = ["experiment=quick", f"data.root={data}", *SMALL_MODEL, *FAST_TRAIN, "trainer.max_time=null",
              "trainer.limit_val_batches=0", "logger=none"]
    summary = train_in_process(out, *common, "trainer.max_steps=5", "trainer.accumulate_grad_batches=3")
    assert summary["global_step"] == 5  # 2 batches an epoch at batch 4 (6 rooms): one step an epoch
    last = out / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False, map_location="cpu")[TRAINER_SETTINGS] == {"accumulate_grad_batches": 3}
    with pytest.raises(ValueError, match=r"trainer\.accumulate_grad_batches: 3 -> 1"):
        train_in_process(out, *common, "trainer.max_steps=6", "ckpt_path=last")
    assert train_in_process(out, *common, "trainer.max_steps=6", "trainer.accumulate_grad_batches=3",
                            "ckpt_path=last")["global_step"] == 6
