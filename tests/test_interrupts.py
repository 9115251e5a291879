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


@pytest.fixture
def ctrl_c():
    """Ctrl-C as an interactive process takes it (pytest-xdist's workers ignore SIGINT, and a process that ignores it
    is left to do so: ``nohup``), restored after."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


@pytest.mark.parametrize("sig, status, said", [(signal.SIGINT, 130, "Ctrl-C"), (signal.SIGTERM, 143, "SIGTERM")])
def test_ctrl_c_or_sigterm_stops_spread_train_after_its_step_saves_it_and_a_relaunch_goes_on(tmp_path, sig, status,
                                                                                            said):
    """SIGTERM (a scheduler's preemption) is stopped like Ctrl-C; it ended the run with status 0, a finished job to
    the scheduler, with no word and nothing saved since the last periodic checkpoint."""
    data = make_dataset(tmp_path / "d")
    out = tmp_path / "run"
    args = [str(SCRIPTS / "spread-train"), "experiment=quick", f"data.root={data}", f"out_dir={out}", *SMALL_MODEL,
            *FAST_TRAIN, "trainer.max_steps=100000", "trainer.max_time=null", "trainer.log_every_n_steps=1",
            "checkpoint.every_n_train_steps=100000", "trainer.limit_val_batches=0"]
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "SPREAD_DEBUG")}
    proc = subprocess.Popen(args, env={**env, "WANDB_MODE": "disabled"}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,  # as a terminal starts it: SIGINT not ignored
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 240
        while not list(out.glob("csv/version_*/metrics.csv")) or \
                len(next(out.glob("csv/version_*/metrics.csv")).read_text().splitlines()) < 4:
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[1][-3000:]
            time.sleep(0.2)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == status, stderr[-3000:]
    assert "Traceback" not in stderr
    if sig == signal.SIGINT:
        assert stderr.strip().splitlines()[-1] == "spread-train: interrupted (Ctrl-C)"
    assert f"spread-train: {said}: stopping at the end of this step and saving it" in stderr
    saved = torch.load(out / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")["global_step"]
    assert saved >= 3 and f"interrupted ({said}) at step {saved}:" in stdout  # the steps made are kept (none were)
    assert not (out / "metrics.json").exists()  # not a finished run: a study does not take it for one
    from helpers import train_in_process

    again = train_in_process(out, "experiment=quick", f"data.root={data}", *SMALL_MODEL, *FAST_TRAIN,
                             f"trainer.max_steps={saved + 2}", "trainer.max_time=null", "trainer.limit_val_batches=0",
                             "ckpt_path=last")
    assert again["global_step"] == saved + 2 and again["resumed_from"] == str(out / "checkpoints" / "last.ckpt")


def test_a_study_stops_at_a_training_stage_interrupted_by_ctrl_c(tmp_path, ctrl_c):
    """In a study's process the training stage raises KeyboardInterrupt, which ``StageEngine.attempt`` lets through
    (a stage that raised anything else is recorded as failed and the next one starts), with the steps saved."""
    from lightning.pytorch.callbacks import Callback

    from spread.experiments.stages import StageEngine
    from spread.training.fit import train

    class CtrlC(Callback):  # the user presses Ctrl-C once step 2 is done: step 3 ends the run
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
    assert torch.load(out / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu")["global_step"] == 3

    class Twice(Callback):  # Ctrl-C twice: stop now (Lightning's shutdown exits 1: the study must stop all the same)
        def on_train_batch_end(self, trainer, *args):
            if trainer.global_step == 1:
                os.kill(os.getpid(), signal.SIGINT)
                os.kill(os.getpid(), signal.SIGINT)

    again = tmp_path / "again"
    cfg = compose("train", "experiment=quick", f"data.root={data}", f"out_dir={again}", *SMALL_MODEL, *FAST_TRAIN,
                  "trainer.max_steps=50", "trainer.max_time=null", "trainer.limit_val_batches=0", "logger=none")
    before = signal.getsignal(signal.SIGINT)
    with pytest.raises(KeyboardInterrupt):
        engine.attempt("train/geometry", lambda: train(cfg, run_dir=again, extra_callbacks=[Twice()]), [])
    assert engine.status == {} and signal.getsignal(signal.SIGINT) == before  # Lightning's SIG_IGN not left behind


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
    assert torch.load(last, weights_only=False, map_location="cpu")[TRAINER_SETTINGS] == {
        "accumulate_grad_batches": 3, "gradient_clip_val": 1.0, "gradient_clip_algorithm": "norm",  # the cpu trainer's
        "precision": "32-true", "limit_train_batches": "all", "world_size": 1, "distributed_sampler": False}
    with pytest.raises(ValueError, match=r"trainer\.accumulate_grad_batches: 3 -> 1"):
        train_in_process(out, *common, "trainer.max_steps=6", "ckpt_path=last")
    # another number of processes: each takes a batch a step (a one-process checkpoint resumed by Ray Train's two
    # workers failed inside them, after the driver's checks); refused on the driver, before Ray starts
    from spread.training.fit import check_start

    from helpers import compose

    again = [*common, "trainer.max_steps=6", "trainer.accumulate_grad_batches=3", "ckpt_path=last", f"out_dir={out}"]
    with pytest.raises(ValueError, match=r"trainer\.world_size: 1 -> 2"):
        check_start(compose("train", *again, "trainer=ray", "ray_train.num_workers=2"), out)
    with pytest.raises(ValueError, match=r"trainer\.world_size: 1 -> 2"):
        train_in_process(out, *again[:-1], "trainer.devices=2", "trainer.strategy=ddp")
    with pytest.raises(ValueError, match=r"trainer\.distributed_sampler: False -> True"):  # one Ray worker too: a
        check_start(compose("train", *again, "trainer=ray", "ray_train.num_workers=1"), out)  # distributed loader
    assert train_in_process(out, *common, "trainer.max_steps=6", "trainer.accumulate_grad_batches=3",
                            "ckpt_path=last")["global_step"] == 6


@pytest.mark.parametrize("sig, raised", [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, SystemExit)])
def test_ctrl_c_or_sigterm_inside_a_gradient_accumulation_stops_at_its_step_and_the_resumed_run_is_the_uninterrupted_one(
        tmp_path, ctrl_c, sig, raised):
    """With ``accumulate_grad_batches=4`` a stop between two batches of one step saved a data position the resumed
    run could not take up (a step of fewer batches, batches never trained): the stop waits for the step's end, and
    the resumed run reaches step 4 with the uninterrupted run's weights, bit for bit. SIGTERM too, though Lightning's
    fit puts in its own handler, which stopped at the batch's end and saved nothing."""
    from lightning.pytorch.callbacks import Callback

    from spread.training.fit import train

    class CtrlC(Callback):  # pressed after the second batch of the first step
        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
            if trainer.current_epoch == 0 and batch_idx == 1:
                os.kill(os.getpid(), sig)

    data = make_dataset(tmp_path / "d")
    common = ["experiment=quick", f"data.root={data}", *SMALL_MODEL, *FAST_TRAIN, "data.batch_size=1",
              "trainer.accumulate_grad_batches=4", "trainer.max_time=null", "trainer.limit_val_batches=0",
              "logger=none", "trainer.max_steps=4"]
    whole = tmp_path / "whole"
    train(compose("train", *common, f"out_dir={whole}"), run_dir=whole)
    parts = tmp_path / "parts"
    with pytest.raises(raised) as stop:
        train(compose("train", *common, f"out_dir={parts}"), run_dir=parts, extra_callbacks=[CtrlC()])
    assert raised is KeyboardInterrupt or stop.value.code == 143
    last = parts / "checkpoints" / "last.ckpt"
    assert torch.load(last, weights_only=False, map_location="cpu")["global_step"] == 1  # the step's end
    train(compose("train", *common, f"out_dir={parts}", "ckpt_path=last"), run_dir=parts)
    a, b = (torch.load(p / "checkpoints" / "last.ckpt", weights_only=False, map_location="cpu") for p in (whole, parts))
    assert a["global_step"] == b["global_step"] == 4
    assert all(torch.equal(a["state_dict"][k], b["state_dict"][k]) for k in a["state_dict"])


def test_a_process_that_ignores_ctrl_c_keeps_ignoring_it_while_it_trains(tmp_path):
    """``nohup spread-train …`` (SIGINT ignored): the platform does not make it interruptible."""
    from spread.training.checkpoints import StopAtStep, stop_on_interrupt

    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with stop_on_interrupt(StopAtStep(tmp_path / "last.ckpt")):
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        signal.signal(signal.SIGINT, signal.default_int_handler)
        with stop_on_interrupt(StopAtStep(tmp_path / "last.ckpt")) as stopper:
            os.kill(os.getpid(), signal.SIGINT)
            assert stopper.asked  # the first Ctrl-C asks for a stop, raises nothing
    finally:
        signal.signal(signal.SIGINT, before)


def test_every_private_ray_train_method_the_platform_overrides_is_in_the_installed_ray_with_its_signature():
    """``interruptible_trainer`` (Ctrl-C ends ``spread-train-ray`` with status 130) and ``private_cluster_trainer``
    (no placement-group cleaner on the command's own cluster) override private ``TorchTrainer`` methods. A Ray whose
    trainer renamed one would call the override never, silently: the command would end with status 1 and no word.
    Only the slow Ray Train tests would see that; this one sees it in ``make test``."""
    import inspect

    from ray.train.torch import TorchTrainer

    from spread.training.ray_train import interruptible_trainer, private_cluster_trainer

    overridden = {name: (cls, value) for cls in (interruptible_trainer(), private_cluster_trainer())
                  for name, value in vars(cls).items() if name.startswith("_") and not name.startswith("__")
                  and callable(value)}
    assert set(overridden) == {"_register_sigint_handler", "_create_default_callbacks"}
    for name, (cls, value) in overridden.items():
        assert callable(getattr(TorchTrainer, name, None)), f"{cls.__name__}.{name}: not a method of Ray's trainer"
        ours, rays = (list(inspect.signature(f).parameters) for f in (value, getattr(TorchTrainer, name)))
        assert ours == rays, f"{cls.__name__}.{name}{ours}: Ray's takes {rays}"
