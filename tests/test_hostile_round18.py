"""Hostile inputs, round 18 (docs/robustness.md): a training loss that is no number stops `spread-train` before its
weights are saved; `spread-import` refuses an out_dir inside another dataset or run."""

from __future__ import annotations

import math

import pytest
import torch

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset, train_in_process, user_error

COMMON = ["experiment=quick", *SMALL_MODEL, *FAST_TRAIN, "trainer.limit_val_batches=0", "logger=none",
          "trainer.max_time=null"]


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("r18") / "d")


def _finite(path) -> bool:
    state = torch.load(path, weights_only=True, map_location="cpu")["state_dict"]
    return all(torch.isfinite(v).all() for v in state.values() if v.is_floating_point())


def test_a_loss_that_turns_nan_stops_training_before_a_checkpoint_of_its_weights_is_saved(data, tmp_path,
                                                                                         monkeypatch):
    """The loss of the 6th step is NaN (injected): the periodic checkpoint of step 6 would hold the NaN weights that
    step made. Training stops there with one message naming the step and the value, and every checkpoint on disk
    (steps 2 and 4, last.ckpt at 4) holds finite weights; before, the run trained to max_steps on NaN weights and
    saved them."""
    from spread.model.module import SceneDiffusion

    combine = SceneDiffusion.combine

    def poisoned(self, terms):
        loss = combine(self, terms)
        return loss * float("nan") if self.trainer.global_step >= 5 else loss

    monkeypatch.setattr(SceneDiffusion, "combine", poisoned)
    out = tmp_path / "run"
    with pytest.raises(ValueError, match=r"the training loss was not a number at step 6 \(nan\).*newest: step 4"):
        train_in_process(out, f"data.root={data}", *COMMON, "trainer.max_steps=12", "trainer.log_every_n_steps=5",
                         "checkpoint.every_n_train_steps=2", "data.batch_size=2")
    saved = sorted(p.name for p in (out / "checkpoints").glob("*.ckpt"))
    assert "last.ckpt" in saved and all(_finite(out / "checkpoints" / name) for name in saved), saved
    assert torch.load(out / "checkpoints" / "last.ckpt", weights_only=True, map_location="cpu")["global_step"] == 4


def test_a_loss_that_turns_infinite_is_found_at_the_logging_interval_without_a_checkpoint_between(data, tmp_path,
                                                                                                 monkeypatch):
    """No checkpoint before the end: the read every ``trainer.log_every_n_steps`` steps finds the first step whose
    loss was infinite and stops there, many steps before max_steps."""
    from spread.model.module import SceneDiffusion

    combine, steps = SceneDiffusion.combine, []

    def poisoned(self, terms):
        steps.append(self.trainer.global_step)
        loss = combine(self, terms)
        return loss * float("inf") if self.trainer.global_step == 2 else loss  # the 3rd step only

    monkeypatch.setattr(SceneDiffusion, "combine", poisoned)
    with pytest.raises(ValueError, match=r"not a number at step 3 \(inf\).*no checkpoint of this run was saved"):
        train_in_process(tmp_path / "run", f"data.root={data}", *COMMON, "trainer.max_steps=40",
                         "trainer.log_every_n_steps=4", "checkpoint.every_n_train_steps=100", "data.batch_size=2")
    assert max(steps) == 3  # stopped at the read of step 4


def test_spread_train_with_a_learning_rate_that_overflows_ends_in_one_line(data, tmp_path):
    out = tmp_path / "run"
    line, proc = user_error("spread-train", f"data.root={data}", *COMMON, f"out_dir={out}", "model.lr=1e30",
                            "trainer.max_steps=30", "trainer.log_every_n_steps=2", "data.batch_size=2")
    assert proc.returncode == 1 and line.startswith("spread-train: the training loss was not a number at step "), line
    assert "Lower model.lr (now 1e+30)" in line
