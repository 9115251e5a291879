"""Hostile inputs, round 17 (folders): an ``out_dir`` inside a dataset or inside a training run is refused, in one
line naming the ``out_dir``, the enclosing folder and its kind (``spread.io.enclosing_folder``): a training run in
``<dataset>/train`` put its checkpoints among the scene files the next training reads, a dataset was generated into a
run's ``checkpoints/``. The nestings the platform makes on purpose stay accepted: an evaluation or an export in a
sampling run, the runs and dataset of an ablation, comparison or sweep in its folder, ``paths.runs_dir``'s layout, a
training run's ``previous/<time>`` history, an export in a folder of its own in a dataset (``conf/export.yaml``)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from helpers import FAST_TRAIN, SMALL_MODEL, make_dataset, train_in_process, user_error


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("r17fdata"))


@pytest.fixture(scope="module")
def run(dataset, tmp_path_factory) -> Path:
    """A base model's training run folder after 2 training steps (checkpoints/last.ckpt, metrics.json, ...)."""
    out = tmp_path_factory.mktemp("r17frun") / "run"
    train_in_process(out, "experiment=quick", "model.variant=base", f"data.root={dataset}", "trainer.max_time=null",
                     "trainer.max_steps=2", *SMALL_MODEL, *FAST_TRAIN)
    return out


def files(folder: Path) -> dict[str, int]:
    """Every file and folder under ``folder`` (relative path → size; folders 0)."""
    return {str(p.relative_to(folder)): p.stat().st_size if p.is_file() else 0 for p in sorted(folder.rglob("*"))}


def refusal(out: Path, kind: str, above: Path) -> str:
    return re.escape(f"out_dir={out}: lies inside a {kind}, {above} (")


def test_spread_train_refuses_an_out_dir_inside_the_datasets_train_split_and_writes_nothing_there(dataset):
    before = files(dataset)
    out = dataset / "train"
    line, _ = user_error("spread-train", "experiment=quick", "model.variant=base", f"data.root={dataset}",
                         *SMALL_MODEL, *FAST_TRAIN, f"out_dir={out}", "trainer.max_steps=1")
    assert re.match(f"spread-train: {refusal(out, 'dataset', dataset)}"
                    f"{re.escape(str(dataset / 'assets' / 'index.json'))}\\); spread-train would write", line), line
    assert files(dataset) == before  # no checkpoints, csv or Hydra record among the scene files


def test_spread_generate_refuses_an_out_dir_inside_a_training_runs_checkpoints_folder(run):
    before = files(run)
    out = run / "checkpoints"
    line, _ = user_error("spread-generate", f"out_dir={out}", "rooms=2", "progress=false")
    assert line.startswith(f"spread-generate: out_dir={out}: lies inside a training run, {run} "
                           f"({run / 'checkpoints'}); spread-generate would write its files into it: give an out_dir "
                           f"outside {run}"), line
    assert files(run) == before


def test_spread_sample_refuses_an_out_dir_inside_a_training_run(dataset, run):
    out = run / "samples"
    line, _ = user_error("spread-sample", f"ckpt={run / 'checkpoints' / 'last.ckpt'}", f"data.root={dataset}",
                         f"out_dir={out}", "logger=none", "workers=0")
    assert re.match(f"spread-sample: {refusal(out, 'training run', run)}", line), line
    assert not out.exists()


def test_spread_evaluate_refuses_an_out_dir_inside_a_dataset(dataset):
    before = files(dataset)
    out = dataset / "eval"
    line, _ = user_error("spread-evaluate", f"scenes={dataset / 'test'}", f"reference={dataset}", f"out_dir={out}",
                         "logger=none")
    assert re.match(f"spread-evaluate: {refusal(out, 'dataset', dataset)}", line), line
    assert files(dataset) == before


def test_an_out_dir_inside_a_dataset_or_a_training_run_is_refused_at_any_depth_for_every_command(dataset, run):
    from spread.io import check_folder_kind

    for command, kinds in [("spread-train", {"training run"}), ("spread-generate", {"dataset"}),
                           ("spread-sample", {"sampling run"}), ("spread-evaluate", {"evaluation"}),
                           ("spread-report", {"report"}), ("spread-sweep", {"sweep"}), ("spread-ablate", {"ablation"})]:
        for out in (dataset / "assets" / "x", dataset / "val" / "a" / "b", dataset / "mine"):
            with pytest.raises(ValueError, match=refusal(out, "dataset", dataset)):
                check_folder_kind(out, command, kinds)
        for out in (run / "checkpoints", run / "csv" / "x", run / "mine" / "deeper"):
            with pytest.raises(ValueError, match=refusal(out, "training run", run)):
                check_folder_kind(out, command, kinds)
    # the export's own place in a dataset is beside its parts, never in them (assets, a split, renders, logs)
    for part in ("assets", "test", "renders", "logs"):
        with pytest.raises(ValueError, match=refusal(dataset / part / "mjcf", "dataset", dataset)):
            check_folder_kind(dataset / part / "mjcf", "spread-export", {"export"})
    # nor a training run's previous/<time> for another command than spread-train, nor deeper in it for training
    with pytest.raises(ValueError, match=refusal(run / "previous" / "t" / "s", "training run", run)):
        check_folder_kind(run / "previous" / "t" / "s", "spread-sample", {"sampling run"})
    with pytest.raises(ValueError, match=refusal(run / "previous" / "t" / "x", "training run", run)):
        check_folder_kind(run / "previous" / "t" / "x", "spread-train", {"training run"})


def test_an_out_dir_reached_through_a_link_into_a_dataset_is_refused(dataset, tmp_path):
    from spread.io import check_folder_kind

    (tmp_path / "link").symlink_to(dataset / "train", target_is_directory=True)
    with pytest.raises(ValueError, match=r"lies inside a dataset, " + re.escape(str(dataset))):
        check_folder_kind(tmp_path / "link" / "run", "spread-train", {"training run"})


def test_the_export_documented_in_a_dataset_folder_stays_accepted(dataset, tmp_path):
    """``conf/export.yaml``: ``spread-export scenes=/tmp/rooms/test format=mjcf out_dir=/tmp/rooms/export_mjcf``."""
    from spread.io import check_folder_kind

    check_folder_kind(dataset / "export_mjcf", "spread-export", {"export"})
    check_folder_kind(dataset / "exports" / "usd", "spread-export", {"export"})


def test_the_nestings_the_platform_makes_stay_accepted(dataset, run, tmp_path):
    """An evaluation or an export in a sampling run (README: ``out_dir=/tmp/run/eval``, ``/tmp/run/sceneeval``; ``spread-
    sample evaluate=true``), an ablation's or comparison's ``data/``, ``train/<v>``, ``samples/<v>``, ``eval/<v>``
    (and ``seed<k>/``), a sweep's ``points/<point>``, ``paths.runs_dir``'s ``train/<name>/<time>``, a training run's
    ``previous/<time>`` resumed by spread-train, a training run in its own folder."""
    from spread.io import check_folder_kind

    sampled = tmp_path / "runs" / "sample" / "s"
    (sampled / "scenes").mkdir(parents=True)
    (sampled / "sampling.json").write_text(json.dumps({"fingerprint": {}}))
    (sampled / ".hydra").mkdir()
    (sampled / ".hydra" / "config.yaml").write_text("{}\n")
    check_folder_kind(sampled, "spread-evaluate", {"evaluation", "sampling run"})
    check_folder_kind(sampled / "eval", "spread-evaluate", {"evaluation"})
    check_folder_kind(sampled / "sceneeval", "spread-export", {"export"})
    check_folder_kind(sampled / "mjcf", "spread-export", {"export"})
    for study, mark, command in ((tmp_path / "ablate" / "q", "ablation.json", "spread-ablate"),
                                 (tmp_path / "compare" / "c", "compare.json", "spread-compare")):
        study.mkdir(parents=True)
        (study / mark).write_text("{}")
        check_folder_kind(study, command, {"ablation", "comparison"})
        for base in (study, study / "seed1"):
            check_folder_kind(base / "data", "spread-generate", {"dataset"})
            check_folder_kind(base / "train" / "base", "spread-train", {"training run"})
            check_folder_kind(base / "samples" / "base", "spread-sample", {"sampling run"})
            check_folder_kind(base / "eval" / "base", "spread-evaluate", {"evaluation"})
    sweep = tmp_path / "tune"
    (sweep / "points").mkdir(parents=True)
    check_folder_kind(sweep / "points" / "c0_g0_r0_abc", "spread-sample", {"sampling run"})
    check_folder_kind(sweep / "points" / "lr_abc", "spread-train", {"training run"})
    check_folder_kind(tmp_path / "runs" / "train" / "quick" / "2024-01-01_00-00-00", "spread-train", {"training run"})
    check_folder_kind(tmp_path / "runs" / "report", "spread-report", {"report"})
    check_folder_kind(run, "spread-train", {"training run"})
    check_folder_kind(run / "previous" / "2024-01-01_00-00-00", "spread-train", {"training run"})
    # the tests' (and a user's) work folder holding an asset library beside the dataset is no dataset
    assert (dataset.parent / "assets" / "index.json").exists()
    check_folder_kind(dataset.parent / "eval", "spread-evaluate", {"evaluation"})
    # a home folder with an unrelated checkpoints/ (downloaded weights) is no training run
    home = tmp_path / "home"
    (home / "checkpoints").mkdir(parents=True)
    (home / "checkpoints" / "weights.ckpt").write_bytes(b"x")
    check_folder_kind(home / "runs" / "train", "spread-train", {"training run"})


def test_spread_export_into_a_folder_of_its_own_in_the_dataset_runs_as_documented(dataset, tmp_path):
    """``conf/export.yaml``'s example, typed as a user types it."""
    import shutil
    import subprocess

    from helpers import SCRIPTS

    rooms = tmp_path / "rooms"
    shutil.copytree(dataset, rooms)
    out = rooms / "export_mjcf"
    proc = subprocess.run([str(SCRIPTS / "spread-export"), f"scenes={rooms / 'test'}", "format=mjcf",
                           f"out_dir={out}", "progress=false"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (out / "export.json").exists()
