"""A sweep's trial is its identity (issue 31 item 3): drawn values rounded to 4 significant digits, one point
folder per identity, two trials of one identity never at once (the second waits, then re-uses), and
``max_concurrent`` held by every search."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import pytest

from spread.experiments.points import point_lock
from spread.experiments.sweep import drawn, format_value, point_name, trial_overrides

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset
from test_sweep import spread


def test_drawn_values_keep_four_significant_digits_and_listed_values_stay_as_written():
    config = {"guidance.collision": 0.012345678901234567, "model.lr": 0.00031622776601683794, "sampler": "ddim50",
              "guidance.gravity": "0.001"}
    assert drawn(config) == {"guidance.collision": 0.01235, "model.lr": 0.0003162, "sampler": "ddim50",
                             "guidance.gravity": "0.001"}
    assert trial_overrides(config) == ["guidance.collision=0.01235", "guidance.gravity=0.001", "model.lr=0.0003162",
                                       "sampler=ddim50"]
    assert point_name(config) == "collision0.01235_gravity0.001_lr0.0003162_samplerddim50"
    assert format_value(0.1 + 0.2) == "0.3"  # no 0.30000000000000004 in a folder name or a cell
    # two draws that round alike are one point
    assert point_name({"a": 0.0123449}) == point_name({"a": 0.01234}) != point_name({"a": 0.01236})


def test_every_search_is_limited_to_max_concurrent_trials():
    from ray.tune.search import BasicVariantGenerator, ConcurrencyLimiter

    from spread.experiments.sweep import SweepSettings
    from spread.experiments.tuning import limited, search_spec

    for name, kind in (("random", BasicVariantGenerator), ("optuna", ConcurrencyLimiter)):
        settings = SweepSettings(out_dir="x", search=name, max_concurrent=3)
        searcher = limited(search_spec(name).build(settings), settings.max_concurrent)
        assert isinstance(searcher, kind) and searcher.max_concurrent == 3, name
    assert limited(None, 2).max_concurrent == 2  # grid: Tune's own generator, limited too


def test_a_second_trial_of_the_same_point_waits_for_the_first(tmp_path):
    folder = tmp_path / "points" / "lr0.001_abc123"
    events = []

    def trial(name: str, hold: float) -> None:
        with point_lock(folder):
            events.append(("start", name, time.monotonic()))
            time.sleep(hold)
            events.append(("end", name, time.monotonic()))

    first = threading.Thread(target=trial, args=("first", 0.5))
    first.start()
    time.sleep(0.1)
    second = threading.Thread(target=trial, args=("second", 0.0))
    second.start()
    first.join(5)
    second.join(5)
    assert [(e[0], e[1]) for e in events] == [("start", "first"), ("end", "first"), ("start", "second"),
                                               ("end", "second")]
    assert events[2][2] >= events[1][2]  # the second started only after the first ended
    assert (tmp_path / ".point-locks" / "lr0.001_abc123.lock").exists() and not (tmp_path / "points").exists()


@pytest.mark.slow
def test_a_random_search_that_draws_the_same_setting_twice_trains_it_once(tmp_path):
    """``spread-sweep command=train search=random`` over a one-value choice, two trials at once: one trains, the
    other waits for it and re-uses its run; one folder, one checkpoint history (no last-v1.ckpt)."""
    data = make_dataset(tmp_path / "data")
    out = tmp_path / "lr"
    spread("spread-sweep", "command=train", "experiment=quick", f"data.root={data}", *SMALL_MODEL, *FAST_TRAIN,
           "trainer.max_steps=2", "trainer.max_time=null", "model.lr=choice(0.001)", "search=random",
           "num_samples=2", "max_concurrent=2", "num_cpus=2", "metric=val/loss", "mode=min", f"out_dir={out}")
    points = list((out / "points").iterdir())
    assert len(points) == 1 and points[0].name.startswith("lr0.001_")
    checkpoints = sorted(p.name for p in (points[0] / "checkpoints").iterdir())
    assert "last.ckpt" in checkpoints and not [c for c in checkpoints if "-v1" in c]
    rows = [r for r in __import__("csv").DictReader((out / "results.csv").open())]
    assert len(rows) == 2 and sorted(r["reused"] for r in rows) == ["False", "True"]
    assert {r["point"] for r in rows} == {points[0].name}
    assert json.loads((points[0] / "point.json").read_text())["status"] == "finished"


def test_a_trials_error_is_its_exceptions_own_line():
    from spread.experiments.sweep import error_line

    wrapped = ("\x1b[36mray::ImplicitFunc.train()\x1b[39m (pid=31869, ip=192.0.2.2, repr=sample_trial)\n"
               "  File \"/x/safe_load.py\", line 89, in load_checkpoint\n"
               "    raise FileNotFoundError(f\"{path}: no such checkpoint file\")\n"
               "FileNotFoundError: runs/last.ckpt: no such checkpoint file\n")
    assert error_line(RuntimeError(wrapped)) == "FileNotFoundError: runs/last.ckpt: no such checkpoint file"
    assert error_line(ValueError("")) == "ValueError"


def test_a_sweep_with_relative_paths_runs_its_trials_in_the_launch_folder(tmp_path, monkeypatch):
    """``ckpt=`` and ``data.root=`` relative to where ``spread-sweep`` was launched mean the same in a trial,
    whatever folder Ray Tune gave the trial process."""
    import os

    from spread.experiments.sweep import in_launch_folder

    launch, trial = tmp_path / "launch", tmp_path / "ray_trial"
    launch.mkdir(), trial.mkdir()
    monkeypatch.chdir(trial)
    in_launch_folder({"cwd": str(launch)})
    assert Path(os.getcwd()) == launch
    in_launch_folder({"cwd": str(tmp_path / "not_on_this_node")})  # another node's folder: stays
    assert Path(os.getcwd()) == launch


def test_a_training_point_is_the_weights_it_starts_from_and_not_where_its_data_lies(tmp_path):
    """``model.init_from`` names a file: other weights at that path are another training (a relaunched training sweep
    re-used its points trained from the old weights); the same rooms at another path are the same point (they were
    trained again). The ablation's and comparison's training stages hold the weights' content too."""
    import shutil

    from spread.experiments.stages import init_weights_input, typed_training
    from spread.experiments.sweep import train_point
    from spread.runtime.fingerprint import done_check

    data = tmp_path / "data"
    for split in ("train", "val"):
        (data / split).mkdir(parents=True)
        (data / split / "a.npz").write_bytes(b"room " + split.encode())
    (data / "assets").mkdir()
    (data / "assets" / "index.json").write_text("{}")
    (data / "stats.json").write_text("{}")
    init = tmp_path / "init.ckpt"
    init.write_bytes(b"weights-1")
    plan = {"fixed": ["experiment=quick", f"data.root={data}", f"model.init_from={init}"], "name": "s",
            "points": str(tmp_path / "points")}
    (tmp_path / "points").mkdir()
    folder, first, _ = train_point({"model.lr": 0.001}, plan)
    recorded = {"overrides": plan["fixed"], **init_weights_input(plan["fixed"])}  # a stage's inputs, when planned
    stage = typed_training(recorded)
    init.write_bytes(b"weights-2")
    _, other, _ = train_point({"model.lr": 0.001}, plan)
    assert done_check(first, other, present=True, finished=True).reason == "changed: init_from_sha256"
    now = typed_training({"overrides": plan["fixed"], **init_weights_input(plan["fixed"])})
    assert typed_training(recorded) == stage and now != stage  # the record keeps what the file held then
    assert "init_from_sha256" not in init_weights_input(["experiment=quick", f"data.root={data}"])
    moved = tmp_path / "moved"
    shutil.copytree(data, moved)
    _, there, _ = train_point({"model.lr": 0.001}, {**plan, "fixed": [f"data.root={moved}" if o.startswith("data.root")
                                                                      else o for o in plan["fixed"]]})
    assert done_check(other, there, present=True, finished=True).reuse
