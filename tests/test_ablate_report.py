"""spread-ablate, spread-report and the guidance-weight sweep.

* tables: CSV reads back equal to the records; Markdown / LaTeX hold the rows with the right numbers.
* report: two fake run folders and a real wandb offline run (written by wandb, read back without network)
  → records, a table, one PNG per (metric, weight) with the right points; bad input names the path.
* ablation stages with fake commands: finished stages are skipped, missing outputs redone, changed inputs
  redone or refused, a failing stage blocks only its row.
* the sweep preset: 27 jobs with distinct, deterministic run folders; the wandb sweep names the same ones.
* end to end (tiny model, a few steps, 4 sampling steps, 1 stability run, no FID): the quick preset's
  code path writes the three-row table; a re-run skips every stage; an interrupted sweep resumes.
"""

from __future__ import annotations

import itertools
import json
import os
import re
import signal
import subprocess
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from spread.configs import conf_dir
from spread.experiments.ablation import AblationSpec, run_ablation
from spread.reporting.report import run_report
from spread.reporting.runs import RunError, find_runs, read_runs
from spread.experiments.stages import StageError
from spread.reporting.tables import Column, metric_columns, read_csv, write_tables

METRICS = metric_columns()

from helpers import FAST_TRAIN, SCRIPTS, SMALL_MODEL, compose, make_dataset, run_script, user_error

ROWS = [
    {"variant": "base", "method": "Ours (base)", "grecall": 0.963, "col_mesh": 0.241, "asd": 0.014,
     "stability": 0.934, "fid": None, "kid": None, "n_scenes": 8, "status": "ok"},
    {"variant": "geometry", "method": "+Geometry", "grecall": 0.965, "col_mesh": 0.225, "asd": 0.012,
     "stability": 0.938, "fid": None, "kid": None, "n_scenes": 8, "status": "ok"},
    {"variant": "guidance", "method": "+Guidance", "grecall": 0.1 + 0.2, "col_mesh": 0.121, "asd": 0.007,
     "stability": 0.95, "fid": 12.5, "kid": 0.004, "n_scenes": 8, "status": "ok"},
]
WEIGHTS = ("guidance.collision", "guidance.gravity", "guidance.relation")


# ---- tables ---------------------------------------------------------------------------------------------

def test_tables_round_trip_and_show_the_rows(tmp_path):
    columns = [Column("method", "Method"), *METRICS]
    paths = write_tables(ROWS, columns, tmp_path / "t", caption="Ablation", label="tab:x")
    back = read_csv(paths["csv"])  # every key, None as None, 0.1 + 0.2 bit for bit; ASD in mm, as its header says
    assert [{k: v for k, v in r.items() if k != "asd_mm"} for r in back] == [
        {k: v for k, v in r.items() if k != "asd"} for r in ROWS]
    assert [r["asd_mm"] for r in back] == pytest.approx([1000 * r["asd"] for r in ROWS])
    md = paths["md"].read_text().splitlines()
    body = [line for line in md if line.startswith("| ") and "Method" not in line]
    assert len(body) == 3
    assert body[0].split(" | ")[1:5] == ["0.963", "0.241", "14.0", "0.934"]  # ASD in mm (stored 0.0140 m)
    assert "**0.300**" not in body[2] and "0.300" in body[2] and "**12.50**" not in body[2]  # one FID: not ranked
    assert "**0.121**" in body[2] and "**0.965**" in body[1]  # best Col_mesh (min), best GRecall (max)
    tex = paths["tex"].read_text()
    assert r"\toprule" in tex and r"\label{tab:x}" in tex and r"Col$_{\text{mesh}}\downarrow$" in tex
    assert r"Ours (base) & 0.963 & 0.241 & 14.0 & 0.934 & -- & -- \\" in tex
    assert r"+Guidance & 0.300 & \textbf{0.121} & \textbf{7.0} & \textbf{0.950} & 12.50 & 0.0040 \\" in tex


@pytest.mark.parametrize("geometry, words", [
    ((0.180, 0.160, 0.200), "lower than base's, and the 95 % intervals do not overlap"),
    ((0.220, 0.200, 0.240), "lower than base's, but the 95 % intervals overlap"),
    ((0.300, 0.280, 0.320), "higher than base's, and the 95 % intervals do not overlap"),
])
def test_the_ablation_table_says_in_words_whether_geometry_beats_base_on_col_mesh(tmp_path, geometry, words):
    from spread.experiments.ablation import geometry_reading, write_ablation_table

    rows = [dict(r) for r in ROWS]
    rows[0].update(col_mesh=0.241, col_mesh_lo=0.221, col_mesh_hi=0.262, n_scenes=100)
    rows[1].update(zip(("col_mesh", "col_mesh_lo", "col_mesh_hi"), geometry), n_scenes=100)
    sentence = geometry_reading(rows)
    assert words in sentence
    assert f"{geometry[0]:.3f} [{geometry[1]:.3f}, {geometry[2]:.3f}] against 0.241 [0.221, 0.262]" in sentence
    assert "(100 / 100 scenes)" in sentence
    paths = write_ablation_table(rows, tmp_path / "ablation")
    assert sentence in paths["md"].read_text()
    # no interval, or no base row: nothing is claimed
    assert geometry_reading(ROWS) == "" and geometry_reading(rows[1:]) == ""
    # a +Geometry row sampled with guidance on its geometry features says so where it is compared
    rows[1]["settings"] = {"geometry_scale": 2.0, "guidance.mode": "none"}
    assert geometry_reading(rows).startswith("+Geometry (sampled with geometry_scale=2.0: guidance on its own geometry "
                                             "features, no physics term) against base, unguided Col_mesh")


def test_the_ablation_caption_names_the_rows_it_holds_and_claims_the_same_settings_only_when_they_are(tmp_path):
    """The caption said "base, +geometry perceiver, +guidance (same test graphs, seeds and protocol)" whatever the
    rows: a table of two rows carried over from runs with another sampler and FID setting said so too."""
    from spread.experiments.ablation import write_ablation_table

    rows = [dict(r, settings={"sampler": "ddim-50", "fid.enabled": True}) for r in ROWS[1:]]
    first = write_ablation_table(rows, tmp_path / "same")["md"].read_text().splitlines()[0]
    assert "Ablation: +Geometry, +Guidance (same test graphs, seeds and protocol)" in first
    rows[1]["settings"] = {"sampler": "ddim-2", "fid.enabled": False}
    text = write_ablation_table(rows, tmp_path / "differ")["md"].read_text()
    assert "Ablation: +Geometry, +Guidance (the rows differ in " in text and "same test graphs" not in text
    assert "sampler" in text.splitlines()[0] and "Ours (base)" not in text


def test_ablation_bar_plot_draws_every_row(tmp_path):
    from PIL import Image

    from spread.reporting.plots import ablation_bars

    drawn = ablation_bars(ROWS, METRICS, tmp_path / "a.png", label_key="method")
    assert drawn["col_mesh"] == [0.241, 0.225, 0.121] and drawn["fid"] == [None, None, 12.5]
    assert Image.open(tmp_path / "a.png").size[0] > 500


def test_a_long_row_name_is_wrapped_on_two_lines_under_its_bar_not_cut():
    from spread.reporting.plots import tick_label

    assert tick_label("Ours (base)") == "Ours (base)"
    assert tick_label("Ours (base), +Geometry's time") == "Ours (base),\n+Geometry's time"  # was "Ours (base), +Geo…"
    longest = tick_label("word " * 20)
    assert longest.count("\n") == 1 and longest.endswith("…") and all(len(x) <= 18 for x in longest.split("\n"))


# ---- report ---------------------------------------------------------------------------------------------

def metrics_json(col_mesh: float, grecall: float) -> dict:
    return {"col_mesh": col_mesh, "grecall": grecall, "asd": 0.01, "stability": 0.9, "fid": None,
            "fid_status": "disabled: fid.enabled is false", "n_scenes": 3, "n_objects": 20, "n_failed": 0}


def fake_runs(root: Path) -> dict[str, Path]:
    """A sweep folder with two run folders (weights in .hydra/config.yaml; in sampling.json only), an
    unfinished run, and a wandb offline run written by wandb itself."""
    a = root / "sweep" / "c0.0_g0.001_r0.001"
    (a / ".hydra").mkdir(parents=True)
    (a / ".hydra" / "config.yaml").write_text(yaml.safe_dump(
        {"guidance": {"mode": "refine", "collision": 0.0, "gravity": 0.001, "relation": 0.001}, "seed": 0}))
    (a / "metrics.json").write_text(json.dumps({**metrics_json(0.30, 0.91), "col_mesh_lo": 0.25, "col_mesh_hi": 0.36,
                                                "bootstrap": {"method": "percentile", "unit": "scene",
                                                              "resamples": 500, "level": 0.95, "seed": 3,
                                                              "n_scenes": 3}}))
    b = root / "sweep" / "c0.015_g0.002_r0.0"
    b.mkdir(parents=True)
    (b / "sampling.json").write_text(json.dumps(
        {"samples": 3, "guidance": {"mode": "refine", "collision": 0.015, "gravity": 0.002, "relation": 0.0}}))
    (b / "metrics.json").write_text(json.dumps(metrics_json(0.10, 0.95)))  # from before intervals: bootstrapped
    (b / "per_scene.jsonl").write_text("".join(json.dumps(r) + "\n" for r in per_scene_lines()))  # from these
    unfinished = root / "sweep" / "c0.0075_g0.0_r0.0"
    (unfinished / "scenes").mkdir(parents=True)
    (unfinished / "sampling.json").write_text("{}")
    return {"a": a, "b": b, "unfinished": unfinished}


def per_scene_lines() -> list[dict]:
    """Three evaluated scenes (10 objects; 1 of them colliding in two scenes, none in the third)."""
    def line(k, colliding):
        return {"scene_id": f"g{k}_k0", "error": None, "num_objects": 10, "state": {
            "col_mesh": {"colliding_objects": colliding, "objects": 10}, "grecall": {"matches": 80, "pairs": 90},
            "asd": {"abs_distance_sum": 0.02, "pairs": 2},
            "stability": {"unchanged_pairs": 85, "pairs": 90, "objects": 10, "still_objects": 9,
                          "displacement_ok": 9, "rotation_ok": 10}}}
    return [line(0, 1), line(1, 2), line(2, 0)]


@pytest.fixture
def wandb_run(tmp_path, monkeypatch) -> Path:
    """A wandb offline run (flat dotted sweep keys, as a wandb agent sets them) with metrics in its summary."""
    import wandb

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    run = wandb.init(project="spread", dir=str(tmp_path), mode="offline", name="agent-run",
                     config={"guidance.mode": "refine", "guidance.collision": 0.0075, "guidance.gravity": 0.0,
                             "guidance.relation": 0.002},
                     settings=wandb.Settings(console="off", save_code=False, silent=True))
    run.log({"col_mesh": 0.5, "grecall": 0.5})
    run.summary.update({**metrics_json(0.20, 0.93), "col_mesh_lo": 0.1, "col_mesh_hi": 0.3, "ci_level": 0.95,
                        "ci_resamples": 1000, "ci_seed": 0})  # what spread-evaluate's wandb_log writes
    run.finish()
    found = list((tmp_path / "wandb").glob("offline-run-*"))
    assert len(found) == 1
    return found[0]


def test_report_reads_run_folders_and_a_wandb_offline_run(tmp_path, wandb_run):
    runs = fake_runs(tmp_path)
    result = run_report([str(tmp_path / "sweep"), str(wandb_run)], tmp_path / "report")
    by_name = {r["run"]: r for r in result.records}
    assert set(by_name) == {"c0.0_g0.001_r0.001", "c0.015_g0.002_r0.0", "agent-run"}
    assert [by_name["c0.0_g0.001_r0.001"][w] for w in WEIGHTS] == [0.0, 0.001, 0.001]  # .hydra/config.yaml
    assert [by_name["c0.015_g0.002_r0.0"][w] for w in WEIGHTS] == [0.015, 0.002, 0.0]  # sampling.json
    assert [by_name["agent-run"][w] for w in WEIGHTS] == [0.0075, 0.0, 0.002]  # the .wandb file
    assert by_name["agent-run"]["col_mesh"] == 0.20 and by_name["agent-run"]["kind"] == "wandb"
    assert result.unfinished == [runs["unfinished"]]
    assert len(result.plots) == 6 * 3  # GRecall, Col_mesh, ASD, Stability, FID, KID × three weights
    from spread.reporting.tables import value_column

    for (metric, weight), (png, points) in result.plots.items():
        assert png.exists() and png.name == f"{metric}_vs_{weight.split('.')[-1]}.png"
        shown = value_column(metric).display  # the plots' values in display units: ASD in mm
        expected = sorted((r[weight], shown(r[metric])) for r in result.records if r[metric] is not None)
        assert points == expected, (metric, weight)
    assert result.plots[("col_mesh", "guidance.collision")][1] == [(0.0, 0.30), (0.0075, 0.20), (0.015, 0.10)]
    assert result.plots[("fid", "guidance.gravity")][1] == []  # FID null everywhere: an empty, labelled plot
    table = read_csv(result.tables["csv"])
    assert [(r["run"], r["col_mesh"]) for r in table] == [(r["run"], r["col_mesh"]) for r in result.records]
    md = result.tables["md"].read_text()
    assert "c0.015_g0.002_r0.0" in md
    # intervals: metrics.json's own (a), bootstrapped from per_scene.jsonl with seed 0 (b), the wandb summary's
    from spread.evaluation.bootstrap import bootstrap_intervals

    computed = bootstrap_intervals(per_scene_lines(), seed=0)
    by_name = {r["run"]: r for r in table}
    assert (by_name["c0.0_g0.001_r0.001"]["col_mesh_lo"], by_name["c0.0_g0.001_r0.001"]["ci_seed"]) == (0.25, 3)
    assert by_name["c0.015_g0.002_r0.0"]["col_mesh_lo"] == computed["col_mesh_lo"] == 0.0
    assert by_name["c0.015_g0.002_r0.0"]["col_mesh_hi"] == computed["col_mesh_hi"] == 0.2
    assert (by_name["agent-run"]["col_mesh_hi"], by_name["agent-run"]["ci_resamples"]) == (0.3, 1000)
    assert "0.300 ± 0.055" in md and "0.100 ± 0.100" in md and "0.200 ± 0.100" in md
    assert "seed 0" in md and "seeds [0, 3]" in md
    assert json.loads((tmp_path / "report" / "report.json").read_text())["unfinished"] == [str(runs["unfinished"])]


def test_report_bad_input_names_the_path(tmp_path):
    runs = fake_runs(tmp_path)
    with pytest.raises(RunError, match=f"{tmp_path / 'nope'}: no such folder"):
        find_runs([str(tmp_path / "nope")])
    with pytest.raises(RunError, match="matches nothing"):
        find_runs([str(tmp_path / "sweep" / "x*")])
    with pytest.raises(RunError, match=f"{runs['unfinished']}: no metrics.json"):
        find_runs([str(runs["unfinished"])])
    (tmp_path / "empty").mkdir()
    with pytest.raises(RunError, match=f"{tmp_path / 'empty'}: no metrics.json, and no run folders"):
        find_runs([str(tmp_path / "empty")])
    records, unfinished = read_runs([str(tmp_path / "sweep" / "c0.0*")])  # a glob: unfinished skipped
    assert [r["run"] for r in records] == ["c0.0_g0.001_r0.001", "c0.015_g0.002_r0.0"]
    training = tmp_path / "train" / "wandb" / "offline-run-20260101_000000-abc"  # a training run's wandb record
    (training / "files").mkdir(parents=True)
    (training / "files" / "wandb-summary.json").write_text(json.dumps({"train/loss": 0.3}))
    assert find_runs([str(tmp_path / "*" / "wandb" / "offline-run-*")])[0] == []  # a glob: skipped, not an error
    with pytest.raises(RunError, match="no registered metric in its summary"):  # named: an error
        read_runs([str(training)])
    assert unfinished == [runs["unfinished"]]
    proc = run_script("spread-report", f"runs={tmp_path / 'nope'}", f"out_dir={tmp_path / 'r'}", ok=False)
    assert proc.returncode != 0 and f"{tmp_path / 'nope'}: no such folder" in proc.stderr



def test_a_sampling_run_named_without_its_evaluation_is_told_apart_from_one_still_running(tmp_path):
    """spread-report on the demo's sampling folder said "the run has not finished" of a run that had: it was sampled
    without an evaluation. A finished sampling run is told to be evaluated (how, in place); one whose sampling.json
    still says ``running`` is still sampling; one whose evaluation began has not finished."""
    from spread.reporting.runs import read_run_folder, why_unfinished

    done = tmp_path / "samples"
    (done / "scenes").mkdir(parents=True)
    (done / "sampling.json").write_text(json.dumps({"fingerprint": {"data_root": "/data/rooms"}, "seconds": 3.2}))
    proc = run_script("spread-report", f"runs=[{done}]", f"out_dir={tmp_path / 'r'}", ok=False)
    assert proc.returncode != 0
    assert (f"runs: {done}: no metrics.json: its scenes are sampled but not evaluated (yet, or sampled without "
            f"evaluate=true); give its evaluation's folder, or evaluate it in place: spread-evaluate "
            f"scenes={done / 'scenes'} out_dir={done} reference=/data/rooms") in " ".join(proc.stderr.split())
    spaced = tmp_path / "my samples"  # a line to paste: quoted where the shell needs it; a record without the data
    (spaced / "scenes").mkdir(parents=True)
    (spaced / "sampling.json").write_text(json.dumps({"fingerprint": {}}))
    assert why_unfinished(spaced).endswith(f"spread-evaluate 'scenes={spaced / 'scenes'}' 'out_dir={spaced}' "
                                           f"reference=<the dataset>")
    assert not (tmp_path / "r").exists()
    (done / "sampling.json").write_text(json.dumps({"fingerprint": {}, "status": "running"}))
    assert why_unfinished(done) == (f"no metrics.json: it is still sampling, or was stopped "
                                    f"({done / 'sampling.json'}: status running)")
    (done / "sampling.json").write_text("{")
    assert why_unfinished(done).startswith(f"no metrics.json, and its sampling.json is unreadable: "
                                           f"{done / 'sampling.json'}: not valid JSON")
    (done / "protocol.json").write_text("{}")  # its evaluation began
    assert why_unfinished(done) == "no metrics.json (the run has not finished)"
    with pytest.raises(RunError, match="no metrics.json \\(the run has not finished\\)"):
        read_run_folder(done)

# ---- ablation stages (fake commands) ----------------------------------------------------------------------

def args(overrides: list[str]) -> dict:
    return dict(o.split("=", 1) for o in overrides)


class FakeCommands:
    """Writes each command's outputs like the real one would (atomic end markers), records the calls."""

    #: seconds per training step of each trained row (the clock the equal-time row is sized by)
    STEP_SECONDS = {"base": 0.1, "geometry": 0.27, "base_time": 0.1}

    def __init__(self, fail_guidance: bool = False):
        self.calls: list[tuple[str, str, str | None]] = []
        self.fail_guidance = fail_guidance
        self.trained: dict[str, dict] = {}  # run folder name -> its overrides

    def generate(self, overrides):
        out = Path(args(overrides)["out_dir"])
        (out / "test").mkdir(parents=True, exist_ok=True)
        (out / "manifest.json").write_text("{}")
        self.calls.append(("generate", str(out), None))

    def train(self, overrides, run_dir):
        (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
        (run_dir / "checkpoints" / "last.ckpt").write_bytes(str(run_dir).encode())
        (run_dir / "metrics.json").write_text("{}")
        steps = int(args(overrides).get("trainer.max_steps", 100))
        seconds = steps * self.STEP_SECONDS[run_dir.name]
        (run_dir / "clock.jsonl").write_text(json.dumps({"step": steps, "scenes": 16 * steps, "seconds": seconds}))
        self.trained[run_dir.name] = args(overrides)
        self.calls.append(("train", run_dir.name, args(overrides)["ckpt_path"]))

    def sample(self, overrides):
        from spread.io import file_sha256

        a = args(overrides)
        out = Path(a["out_dir"])
        self.calls.append(("sample", out.name, a["resume"]))
        if self.fail_guidance and "guidance" in a:
            raise RuntimeError("guidance exploded")
        (out / "scenes").mkdir(parents=True, exist_ok=True)
        if a["resume"] == "false":
            for f in (out / "scenes").glob("*.npz"):
                f.unlink()
        for i in range(2):
            (out / "scenes" / f"g{i}.npz").write_bytes(b"x")
        (out / "sampling.json").write_text(json.dumps(
            {"samples": 2, "fingerprint": {"ckpt_sha256": file_sha256(a["ckpt"]), "seed": a["seed"]},
             "guidance": a.get("guidance")}))

    def evaluate(self, overrides):
        a = args(overrides)
        out = Path(a["out_dir"])
        out.mkdir(parents=True, exist_ok=True)
        value = {"base": 0.3, "base_time": 0.25, "geometry": 0.2, "guidance": 0.1}[out.name]
        (out / "metrics.json").write_text(json.dumps(metrics_json(value, 1 - value)))
        self.calls.append(("evaluate", out.name, a["resume"]))
        return {}


def spec(tmp_path: Path, **kw) -> AblationSpec:
    defaults = dict(out_dir=tmp_path / "abl", train=["seed=0"], train_variant={"base": ["experiment=paper_base"],
                    "geometry": ["experiment=paper_geometry"]}, sample=["seed=0"], guidance=["guidance=refine"],
                    evaluate=["seed=0"], generate=["rooms=4"], figures=False)  # fake scenes: nothing to draw
    return AblationSpec(**{**defaults, **kw})


def test_ablation_resumes_stage_by_stage(tmp_path):
    commands = FakeCommands()
    first = run_ablation(spec(tmp_path), commands)
    assert first.ok and set(first.stages.values()) == {"done"}
    assert [c[0] for c in commands.calls] == ["generate", "train", "train", *["sample"] * 3, *["evaluate"] * 3]
    assert [(r["variant"], r["col_mesh"]) for r in first.records] == [("base", 0.3), ("geometry", 0.2),
                                                                       ("guidance", 0.1)]
    assert read_csv(tmp_path / "abl" / "ablation.csv")[2]["col_mesh"] == 0.1
    assert all(p.exists() for p in first.tables.values())

    commands.calls.clear()  # everything finished: nothing runs, the table stays
    logged = []
    again = run_ablation(spec(tmp_path), commands, lambda records, png: logged.append([r["variant"] for r in records]))
    assert commands.calls == [] and set(again.stages.values()) == {"skipped"}
    assert logged == [["base", "geometry", "guidance"]]  # this launch's tracker run shows the table (it was empty)

    out = tmp_path / "abl"
    (out / "eval" / "geometry" / "metrics.json").unlink()      # a missing output: that stage only, resumed
    (out / "samples" / "base" / "scenes" / "g1.npz").unlink()  # a missing scene: sampling resumes
    (out / "train" / "base" / "metrics.json").unlink()         # training interrupted: continue from last.ckpt
    again = run_ablation(spec(tmp_path), commands)
    assert commands.calls == [("train", "base", str(out / "train" / "base" / "checkpoints" / "last.ckpt")),
                              ("sample", "base", "true"), ("evaluate", "geometry", "true")]
    assert again.stages["table"] == "skipped"  # same rows

    commands.calls.clear()  # a changed checkpoint: its samples and their evaluations are redone from scratch
    (out / "train" / "geometry" / "checkpoints" / "last.ckpt").write_bytes(b"retrained")
    run_ablation(spec(tmp_path), commands)
    assert commands.calls == [("sample", "geometry", "false"), ("sample", "guidance", "false"),
                              ("evaluate", "geometry", "false"), ("evaluate", "guidance", "false")]

    from spread.experiments.ablation import Ablation
    from spread.experiments.stages import run_stage

    ablation = Ablation(spec(tmp_path), commands)  # a training stage found changed mid-run: refused by its folder
    with pytest.raises(StageError, match=f"{out / 'train' / 'base'}: made with other settings"):
        run_stage(replace(ablation.engine.train_stage("base"), inputs={"overrides": ["seed=1"]}), ablation.engine.ledger)
    # a relaunch with other training settings: refused before any stage runs, the published table as it was
    table = {p.name: p.read_bytes() for p in out.glob("ablation.*")}
    ledger = (out / "ablation.json").read_bytes()
    commands.calls.clear()
    with pytest.raises(ValueError, match=f"train/base: {out / 'train' / 'base'}: made with other settings"):
        run_ablation(spec(tmp_path, train=["seed=1"]), commands)
    assert commands.calls == [] and (out / "ablation.json").read_bytes() == ledger
    assert {p.name: p.read_bytes() for p in out.glob("ablation.*")} == table
    import shutil  # doing what the error says — deleting that folder — lets the stage train anew

    shutil.rmtree(out / "train" / "base")
    shutil.rmtree(out / "train" / "geometry")
    commands.calls.clear()
    changed = run_ablation(spec(tmp_path, train=["seed=1"]), commands)
    assert changed.stages["train/base"] == "done" and ("train", "base", "null") in commands.calls


class KilledDuringSample(FakeCommands):
    """A driver stopped (SIGTERM, a lost node) while one row samples: some scenes written, nothing recorded."""

    def __init__(self, row: str):
        super().__init__()
        self.row = row

    def sample(self, overrides):
        a = args(overrides)
        if Path(a["out_dir"]).name != self.row:
            return super().sample(overrides)
        self.calls.append(("sample", self.row, a["resume"]))
        scenes = Path(a["out_dir"]) / "scenes"
        for f in scenes.glob("*.npz"):  # resume=false: the older run's scenes go first, as the real command does
            f.unlink()
        (scenes / "g0.npz").write_bytes(b"new")
        raise KeyboardInterrupt  # not an Exception: nothing catches it, as nothing catches a killed process


def test_a_driver_stopped_mid_stage_after_a_change_continues_that_stage_instead_of_redoing_it(tmp_path):
    """Relaunched with the settings it was stopped with, the stage continues (resume=true: the command keeps the
    scenes its own record says were made with them); relaunched with other settings again, it is redone."""
    out = tmp_path / "abl"
    assert run_ablation(spec(tmp_path), FakeCommands()).ok  # finished once with seed 0
    changed = ["seed=0", "graph_scale=2.0"]
    with pytest.raises(KeyboardInterrupt):
        run_ablation(spec(tmp_path, sample=changed, variants=("geometry",)), KilledDuringSample("geometry"))
    assert (out / "samples" / "geometry" / "scenes" / "g0.npz").read_bytes() == b"new"
    commands = FakeCommands()
    assert run_ablation(spec(tmp_path, sample=changed, variants=("geometry",)), commands).ok
    assert ("sample", "geometry", "true") in commands.calls  # continued, not redone from scratch
    assert not list((out / ".begun").glob("*.json"))  # recorded: nothing left begun
    # stopped again with a change, then relaunched with the older settings: what is there is not theirs
    with pytest.raises(KeyboardInterrupt):
        run_ablation(spec(tmp_path, sample=["seed=0", "graph_scale=3.0"], variants=("geometry",)),
                     KilledDuringSample("geometry"))
    commands = FakeCommands()
    assert run_ablation(spec(tmp_path, sample=changed, variants=("geometry",)), commands).ok
    assert ("sample", "geometry", "false") in commands.calls


def test_a_failing_row_blocks_only_itself(tmp_path):
    commands = FakeCommands(fail_guidance=True)
    result = run_ablation(spec(tmp_path), commands)
    assert not result.ok and result.stages["sample/guidance"] == "failed"
    assert result.stages["evaluate/guidance"] == "blocked" and result.stages["evaluate/geometry"] == "done"
    assert "guidance exploded" in result.errors["sample/guidance"]
    rows = read_csv(tmp_path / "abl" / "ablation.csv")
    assert [r["col_mesh"] for r in rows] == [0.3, 0.2, None] and "not run" in rows[2]["status"]
    commands.fail_guidance = False  # fixed: only the guidance row and the table run again
    commands.calls.clear()
    result = run_ablation(spec(tmp_path), commands)
    assert result.ok and [c[:2] for c in commands.calls] == [("sample", "guidance"), ("evaluate", "guidance")]
    assert result.stages["table"] == "done" and read_csv(tmp_path / "abl" / "ablation.csv")[2]["col_mesh"] == 0.1


def test_the_equal_time_row_trains_base_for_geometrys_training_seconds(tmp_path):
    """base_time: base's overrides, trained after base and +Geometry for the steps base makes in +Geometry's
    clock time (here 100 geometry steps of 0.27 s, base 0.1 s a step: 270 steps), sampled and evaluated unguided."""
    from spread.experiments.ablation import geometry_reading

    commands = FakeCommands()
    result = run_ablation(spec(tmp_path, variants=("base_time", "geometry")), commands)
    assert result.ok and [c[1] for c in commands.calls if c[0] == "train"] == ["base", "geometry", "base_time"]
    assert commands.trained["base_time"]["trainer.max_steps"] == "270"
    assert commands.trained["base_time"]["experiment"] == "paper_base"
    assert [(r["variant"], r["method"], r["col_mesh"]) for r in result.records] == [
        ("base_time", "Ours (base), +Geometry's time", 0.25), ("geometry", "+Geometry", 0.2)]
    commands.calls.clear()  # a re-run sizes it the same from the same clocks: nothing runs
    assert run_ablation(spec(tmp_path, variants=("base_time", "geometry")), commands).ok and commands.calls == []
    # the table's sentence reads +Geometry against both base rows
    rows = [{"variant": v, "col_mesh": c, "col_mesh_lo": c - 0.02, "col_mesh_hi": c + 0.02, "n_scenes": 100}
            for v, c in (("base", 0.30), ("base_time", 0.22), ("geometry", 0.20))]
    sentence = geometry_reading(rows)
    assert "+Geometry against base, unguided Col_mesh (100 / 100 scenes): 0.200 [0.180, 0.220] against 0.300" \
        in sentence and "do not overlap" in sentence
    assert ("+Geometry against base at equal training time, unguided Col_mesh (100 / 100 scenes): 0.200 [0.180, "
            "0.220] against 0.220 [0.200, 0.240], lower than base's, but the 95 % intervals overlap") in sentence


class PerSceneCommands(FakeCommands):
    """FakeCommands whose evaluations also write per-scene Col_mesh on the same 40 scene ids: +Geometry 0.1 below
    base on every scene, and alike base_time's on average (above on half the scenes, below on the others)."""

    def evaluate(self, overrides):
        out = Path(args(overrides)["out_dir"])
        result = super().evaluate(overrides)
        shift = {"base": 0.1, "base_time": 0.0, "geometry": 0.0, "guidance": -0.05}[out.name]
        lines = []
        for k in range(40):
            value = 0.2 + shift + (0.05 * (-1) ** k if out.name == "base_time" else 0.0) + 0.01 * (k % 3)
            lines.append(json.dumps({"scene_id": f"g{k:02d}", "col_mesh": value}))
        (out / "per_scene.jsonl").write_text("\n".join(lines) + "\n")
        metrics = json.loads((out / "metrics.json").read_text())
        metrics.update(col_mesh_lo=metrics["col_mesh"] - 0.05, col_mesh_hi=metrics["col_mesh"] + 0.05,
                       bootstrap={"method": "percentile", "unit": "scene", "resamples": 1000, "level": 0.95,
                                  "seed": 0, "n_scenes": 40})
        (out / "metrics.json").write_text(json.dumps(metrics))
        return result


def test_the_table_reads_geometry_against_each_base_row_paired_on_the_same_scenes(tmp_path):
    result = run_ablation(spec(tmp_path, variants=("base", "base_time", "geometry")), PerSceneCommands())
    assert result.ok
    paired = next(r for r in result.records if r["variant"] == "geometry")["paired"]
    assert paired["base"]["n_pairs"] == 40 and paired["base"]["diff"] == pytest.approx(-0.1)
    assert paired["base"]["hi"] < 0 and paired["base_time"]["lo"] < 0 < paired["base_time"]["hi"]
    md = (tmp_path / "abl" / "ablation.md").read_text()
    assert ("Paired on the same 40 scenes (the mean of per-scene Col_mesh differences), +Geometry − Ours (base): "
            "-0.100 [-0.100, -0.100], below zero: lower on the same scenes.") in md
    assert "+Geometry − Ours (base), +Geometry's time: " in md and "it spans zero." in md


def test_the_equal_time_row_needs_both_clocks(tmp_path):
    import torch

    ckpt = tmp_path / "g.ckpt"
    torch.save({"hyper_parameters": {"variant": "geometry"}, "state_dict": {}}, ckpt)
    result = run_ablation(spec(tmp_path, variants=("base_time", "geometry"), ckpt={"geometry": str(ckpt)}),
                          FakeCommands())
    assert result.stages["train/base_time"] == "failed" and result.stages["sample/base_time"] == "blocked"
    assert "needs base and +Geometry trained in this ablation" in result.errors["train/base_time"]
    assert "train/geometry/clock.jsonl" in result.errors["train/base_time"]
    assert result.stages["evaluate/geometry"] == "done"
    # a clock cut mid-line by a kill: named, not a traceback
    clock = tmp_path / "abl" / "train" / "base" / "clock.jsonl"
    clock.write_text('{"step": 100, "scenes": 1600, "seconds": 10.0}\n{"step": 200, "sec')
    result = run_ablation(spec(tmp_path, variants=("base_time", "geometry")), FakeCommands())
    assert f"{clock}: the last line is not a clock record" in result.errors["train/base_time"]


def test_given_checkpoints_skip_training_and_bad_specs_name_the_key(tmp_path):
    import torch

    ckpt = tmp_path / "g.ckpt"
    torch.save({"hyper_parameters": {"variant": "geometry"}, "state_dict": {}}, ckpt)  # what the +Geometry row needs
    commands = FakeCommands()
    result = run_ablation(spec(tmp_path, variants=("geometry", "guidance"), ckpt={"geometry": str(ckpt)}), commands)
    assert result.stages["train/geometry"] == "given" and "train/base" not in result.stages
    assert [r["variant"] for r in result.records] == ["geometry", "guidance"]
    assert not [c for c in commands.calls if c[0] == "train"]
    with pytest.raises(ValueError, match="variants"):
        spec(tmp_path, variants=("bogus",))
    with pytest.raises(FileNotFoundError, match="train.ckpt.base=/nope.ckpt"):
        spec(tmp_path, ckpt={"base": "/nope.ckpt"})


def test_a_trained_row_whose_lists_compose_another_model_is_refused_before_any_stage(tmp_path):
    """A ``train.geometry`` list given on the command line replaces the preset's: without ``model.variant=geometry``
    the +Geometry row trained a second base model under +Geometry's name (stop 48, 1,320 graphs: two equal rows).
    Refused in one line naming the list, before anything trains, for the script as users type it and the library."""
    last, _ = user_error("spread-ablate", "+preset=quick", f"data.root={tmp_path / 'data'}", f"out_dir={tmp_path / 'abl'}",
                         "variants=[base,geometry]", "logger=none", 'train.geometry=["model.config.geometry_summary=true"]')
    assert last.startswith("spread-ablate: train.geometry: the +Geometry row trains model.variant=geometry"), last
    assert "compose model.variant=base" in last
    assert not (tmp_path / "data").exists() and not (tmp_path / "abl" / "train").exists()  # nothing generated
    commands = FakeCommands()
    with pytest.raises(ValueError, match=r"train\.base: the Ours \(base\) row trains model\.variant=base, but "
                                         r".*compose model\.variant=geometry"):
        run_ablation(spec(tmp_path, variants=("base_time",),
                          train_variant={"base": ["experiment=paper_geometry"], "geometry": ["experiment=paper_geometry"]}),
                     commands)
    assert commands.calls == []
    # a given checkpoint is not trained: its lists are not asked (check_given checks the file's kind)
    ckpt = tmp_path / "g.ckpt"
    import torch

    torch.save({"hyper_parameters": {"variant": "geometry"}, "state_dict": {}}, ckpt)
    run_ablation(spec(tmp_path, variants=("geometry",), ckpt={"geometry": str(ckpt)},
                      train_variant={"geometry": ["experiment=paper_base"]}), commands)


def test_presets_compose_and_an_unknown_preset_is_named():
    from spread.commands.ablate import ablation_spec

    quick = ablation_spec(compose("ablate", "+preset=quick"))
    assert quick.out_dir == Path("runs/ablate/quick") and "sampler=ddim50" in quick.sample
    paper = ablation_spec(compose("ablate", "+preset=paper"))
    assert "sampler=ddpm" in paper.sample and "trainer=gpu" in paper.train
    assert {"guidance.collision=7.5e-3", "guidance.gravity=1.0e-3", "guidance.relation=1.0e-3"} <= set(paper.guidance)
    for preset in (quick, paper):  # every sub-command list composes with its command's config
        for v in ("base", "geometry"):
            cfg = compose("train", *preset.train, *preset.train_variant[v], "data.root=/d", "out_dir=/o")
            assert cfg.model.variant == v
        sample = compose("sample", *preset.sample, *preset.guidance, "ckpt=c", "data.root=/d", "out_dir=/o")
        assert sample.guidance.mode == "refine"
        compose("evaluate", *preset.evaluate, "scenes=/s", "reference=/d", "out_dir=/o")
        compose("generate", *preset.generate, "out_dir=/o")
    proc = run_script("spread-ablate", "+preset=nope", ok=False)
    assert proc.returncode != 0 and "preset/nope" in proc.stderr and "quick" in proc.stderr


# ---- the sweep preset -----------------------------------------------------------------------------------

def sweep_jobs(*overrides: str) -> list[list[str]]:
    """The jobs ``spread-sample -m +sweep=guidance_grid ...`` launches (Hydra's basic sweeper expansion)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    cfg = compose_hydra("sample", "+sweep=guidance_grid", *overrides)
    params = [f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()]
    parsed = OverridesParser.create().parse_overrides([*params, *overrides])
    return [list(job) for batch in BasicSweeper.split_arguments(parsed, None) for job in batch]


def compose_hydra(name: str, *overrides: str):
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    from spread.configs import register

    register(name)
    with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):
        return hydra_compose(config_name=name, overrides=list(overrides), return_hydra_config=True)


def test_sweep_preset_is_27_jobs_in_distinct_deterministic_folders():
    base = ["ckpt=c.ckpt", "data.root=/d"]
    jobs = sweep_jobs(*base)
    assert len(jobs) == 27
    folders = []
    for job in jobs:
        cfg = compose_hydra("sample", "+sweep=guidance_grid", *job)
        assert cfg.evaluate is True and cfg.guidance.mode == "refine"
        # the point's folder: its weights and short fingerprint; Hydra's own records: this launch's folder
        assert re.fullmatch(r"runs/sweeps/guidance_grid/c[0-9.e-]+_g[0-9.e-]+_r[0-9.e-]+_[0-9a-f]{8}", cfg.out_dir)
        assert str(cfg.hydra.sweep.dir).startswith("runs/sweeps/guidance_grid/.launches/")
        folders.append(cfg.out_dir)
    assert len(set(folders)) == 27
    assert "${now" not in str(compose_hydra("sample", "+sweep=guidance_grid", *base).hydra.sweep)
    assert folders[::13] == [compose_hydra("sample", "+sweep=guidance_grid", *job).out_dir for job in jobs[::13]]
    grid = {(c, g, r) for c, g, r in itertools.product([0.0, 0.0075, 0.03], [0.0, 0.001, 0.004], [0.0, 0.001, 0.004])}
    assert {f"runs/sweeps/guidance_grid/c{c}_g{g}_r{r}" for c, g, r in grid} == {f.rsplit("_", 1)[0] for f in folders}
    # the wandb sweep file: same grid, same command, so a wandb agent's runs land in the same kind of folders
    wandb_sweep = yaml.safe_load((Path(conf_dir()).parent / "sweeps" / "guidance_weights.yaml").read_text())
    values = [wandb_sweep["parameters"][w]["values"] for w in WEIGHTS]
    assert {tuple(v) for v in itertools.product(*values)} == grid and wandb_sweep["method"] == "grid"
    command = wandb_sweep["command"]
    assert "${args_no_hyphens}" in command and "evaluate=true" in command and "+sweep=guidance_grid" in command
    fixed = [c.replace("${envvar:SPREAD_CKPT}", "c.ckpt").replace("${envvar:SPREAD_DATA}", "/d") for c in command
             if not c.startswith("${")]
    cfg = compose_hydra("sample", *fixed, "guidance.collision=0.015", "guidance.gravity=0.0", "guidance.relation=0.001")
    assert re.search(r"/c0.015_g0.0_r0.001_[0-9a-f]{8}$", cfg.out_dir) and cfg.evaluate is True
    assert cfg.logger.mode == "online"  # a wandb agent's runs report to the controller


# ---- end to end -----------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_ablation(tmp_path_factory):
    """The quick preset's code path on 12 generated rooms (3 test graphs) with a shrunken model."""
    import torch

    from spread.commands.ablate import ablate as run

    torch.set_num_threads(1)
    data = make_dataset(tmp_path_factory.mktemp("abdata"))
    out = tmp_path_factory.mktemp("ablate") / "quick"
    cfg = compose("ablate", "+preset=quick", f"data.root={data}", f"out_dir={out}",
                  "variants=[base,geometry,guidance]")  # the one-term rows: tests/test_ablate_seeds.py
    cfg.train.extra = [*SMALL_MODEL, *FAST_TRAIN, "trainer.max_steps=3", "trainer.max_time=null"]
    cfg.sample.extra = ["sampler.steps=4", "progress=false", "renders=1", "figures=0", "batch_size=2"]
    cfg.evaluate.extra = ["protocol.stability_runs=1", "fid.enabled=false", "renders=0", "progress=false"]
    started = time.perf_counter()
    result = run(cfg)
    return {"cfg": cfg, "result": result, "out": out, "data": data, "seconds": time.perf_counter() - started}


def test_tiny_ablation_end_to_end_and_resume(tiny_ablation, monkeypatch):
    from spread.commands.ablate import ablate as run

    result, out = tiny_ablation["result"], tiny_ablation["out"]
    assert result.ok, result.errors
    assert [r["variant"] for r in result.records] == ["base", "geometry", "guidance"]
    for r in result.records:
        assert r["n_scenes"] == 3 and all(0.0 <= r[k] <= 1.0 for k in ("grecall", "col_mesh", "stability"))
        assert r["asd"] is None or r["asd"] >= 0.0
        assert r["fid"] is None and r["fid_status"].startswith("disabled")
    rows = read_csv(out / "ablation.csv")
    assert [(r["variant"], r["grecall"]) for r in rows] == [(r["variant"], r["grecall"]) for r in result.records]
    assert "+Guidance" in (out / "ablation.tex").read_text() and (out / "ablation.png").stat().st_size > 0
    # every cell with its bootstrap interval (bounds and seed in the CSV), one scene per row drawn in 3D
    for r in rows:
        assert r["grecall_lo"] <= r["grecall"] <= r["grecall_hi"] and r["ci_resamples"] == 1000 and r["ci_seed"] == 0
    md = (out / "ablation.md").read_text()
    assert " ± " in md and "bootstrap interval over scenes (1,000 resamples, seed 0)" in md
    # each row names what differs: the checkpoint (base vs geometry), the guidance (its mode, each weight)
    assert [r["guidance.mode"] for r in rows] == ["none", "none", "refine"] and rows[2]["guidance.gravity"] == 0.004
    assert str(rows[0]["ckpt"]) != str(rows[1]["ckpt"]) and str(rows[1]["ckpt"]) == str(rows[2]["ckpt"])
    assert "What differs between the rows" in md and "guidance.mode=refine, guidance.collision=0.0075" in md
    assert r"$\pm$" in (out / "ablation.tex").read_text()
    for v in ("truth", "base", "geometry", "guidance"):
        assert (out / f"ablation_{v}.png").stat().st_size > 10_000 and f"(ablation_{v}.png)" in md
    # same graphs, same seeds: the three rows sampled the same files; guidance recorded only in its row
    names = [sorted(p.name for p in (out / "samples" / v / "scenes").glob("*.npz"))
             for v in ("base", "geometry", "guidance")]
    assert names[0] == names[1] == names[2] and len(names[0]) == 3
    manifests = {v: json.loads((out / "samples" / v / "sampling.json").read_text()) for v in ("geometry", "guidance")}
    assert manifests["guidance"]["guidance"]["mode"] == "refine" and not manifests["geometry"].get("guidance")
    assert manifests["guidance"]["fingerprint"]["ckpt_sha256"] == manifests["geometry"]["fingerprint"]["ckpt_sha256"]
    assert manifests["guidance"]["fingerprint"]["sampling"] == manifests["geometry"]["fingerprint"]["sampling"]
    protocols = {json.dumps(json.loads((out / "eval" / v / "metrics.json").read_text())["protocol"], sort_keys=True)
                 for v in ("base", "geometry", "guidance")}
    assert len(protocols) == 1  # one protocol for every row
    assert (out / "train" / "base" / ".hydra" / "config.yaml").exists()
    report = {r["run"]: r for r in run_report([str(out)], out / "report").records}  # eval/<v> → samples/<v>
    assert set(report) == {"base", "geometry", "guidance"} and report["base"]["guidance.mode"] == "none"
    assert [report["base"][w] for w in WEIGHTS] == [0.0, 0.0, 0.0]  # unguided: no term acts
    assert [report["guidance"][w] for w in WEIGHTS] == [0.0075, 0.004, 0.001]  # the quick preset's weights
    assert report["base"]["ckpt"] != report["geometry"]["ckpt"]  # each row names the checkpoint it sampled
    stamp = (out / "ablation.csv").stat().st_mtime_ns
    import spread.runtime.ray as spread_ray

    def no_ray(*args, **kwargs):
        raise AssertionError("a re-run of a finished ablation must not start Ray for its rows")

    monkeypatch.setattr(spread_ray, "ray_session", no_ray)
    again = run(tiny_ablation["cfg"])
    assert again.stages.pop("data") == "given" and set(again.stages.values()) == {"skipped"}, again.stages
    assert (out / "ablation.csv").stat().st_mtime_ns == stamp and again.records == result.records


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_interrupted_sweep_skips_finished_runs(tiny_ablation, tmp_path):
    """Two grid points; the sweep is killed (SIGKILL to its process group, like a preemption) right after the
    first run's metrics.json, then launched again: the finished run is left as it is, the other one completes."""
    out = tiny_ablation["out"]
    sweep = tmp_path / "sweep"
    ckpt = out / "train" / "geometry" / "checkpoints" / "last.ckpt"
    cmd = [str(SCRIPTS / "spread-sample"), "-m", "+sweep=guidance_grid", f"ckpt={ckpt}",
           f"data.root={tiny_ablation['data']}", f"sweep_dir={sweep}", "guidance.collision=0.0,0.015",
           "guidance.gravity=0.001", "guidance.relation=0.001", "sampler.steps=4", "workers=0", "batch_size=2",
           "renders=0", "progress=false", "logger=none", "evaluation.protocol.stability_runs=1",
           "evaluation.fid.enabled=false", "ray.num_cpus=2"]
    env = {**os.environ, "WANDB_MODE": "disabled", "HYDRA_FULL_ERROR": "1"}
    log = tmp_path / "first_launch.log"
    with open(log, "w") as fh:  # a file, not a pipe: a full pipe would stall the sweep
        proc = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.time() + 300
        while not list(sweep.glob("c0.0_g0.001_r0.001_*/metrics.json")) and proc.poll() is None \
                and time.time() < deadline:
            time.sleep(0.05)
        assert list(sweep.glob("c0.0_g0.001_r0.001_*/metrics.json")), log.read_text()[-3000:]
        first = next(sweep.glob("c0.0_g0.001_r0.001_*"))
        os.killpg(proc.pid, signal.SIGKILL)  # preempted: the sweep and every process it started (its Ray)
        proc.wait(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not list(sweep.glob("c0.015_g0.001_r0.001_*/metrics.json"))
    stamps = {p: p.stat().st_mtime_ns for p in [first / "metrics.json", first / "per_scene.jsonl",
                                                *sorted((first / "scenes").glob("*.npz"))]}
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps, \
        "spread-sample must skip a run folder whose metrics.json exists (spread.reporting.runs.is_finished_run)"
    second = next(sweep.glob("c0.015_g0.001_r0.001_*"))
    metrics = json.loads((second / "metrics.json").read_text())
    assert metrics["n_scenes"] == 3 and metrics["n_failed"] == 0
    report = run_report([str(sweep)], tmp_path / "report")
    assert [r["guidance.collision"] for r in report.records] == [0.0, 0.015]
    assert np.isfinite([r["col_mesh"] for r in report.records]).all()


def test_wandb_ablation_table_carries_the_bounds_and_the_row_figures(tmp_path, monkeypatch):
    """Offline: the logged table has each metric's bounds and the bootstrap's seed; each row's figure is an image."""
    from spread.reporting.wandb_table import log_ablation
    from spread.render import save_png
    from spread.tracking.loggers import LoggerConfig

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    records = [{"variant": v, "method": v, "grecall": 0.8, "grecall_lo": 0.7, "grecall_hi": 0.9, "col_mesh": 0.2,
                "col_mesh_lo": 0.1, "col_mesh_hi": 0.3, "ci_level": 0.95, "ci_resamples": 1000, "ci_seed": 4}
               for v in ("base", "geometry")]
    for k in ("truth", "base"):  # geometry's figure is missing: logged without it
        save_png(np.full((8, 8, 3), 200, np.uint8), tmp_path / f"ablation_{k}.png")
    folder = Path(log_ablation(records, None, tmp_path, LoggerConfig(mode="offline"), name="t"))  # its files/
    tables = list((folder / "media" / "table").glob("ablation_*.table.json"))
    assert len(tables) == 1
    logged = json.loads(tables[0].read_text())
    columns = logged["columns"]
    assert columns[columns.index("grecall"):columns.index("grecall") + 3] == ["grecall", "grecall_lo", "grecall_hi"]
    assert logged["data"][0][columns.index("ci_seed")] == 4
    images = sorted(p.name.split("_")[0] for p in (folder / "media" / "images" / "ablation_figure").glob("*.png"))
    assert images == ["base", "truth"]


def test_an_unguided_run_reports_zero_guidance_weights_not_the_config_defaults():
    from spread.runtime.fingerprint import config_identity, settings

    unguided = settings(config_identity({"guidance": {"mode": "none", "collision": 0.0075, "gravity": 0.001}}))
    guided = settings(config_identity({"guidance": {"mode": "refine", "collision": 0.0075}}))
    assert unguided["guidance.mode"] == "none" and unguided["guidance.collision"] == 0.0
    assert unguided["guidance.box_iou"] == 0.0 and "guidance.iterations" not in unguided  # nothing of it acts
    assert guided["guidance.collision"] == 0.0075 and guided["guidance.gravity"] == 0.001  # the default λ_H
    assert guided["guidance.iterations"] == 100 and guided["guidance.box_iou"] == 0.0


# ---- published tables only grow (issue 31, item 5) ----------------------------------------------------------

def test_a_rerun_with_some_rows_keeps_the_other_finished_rows_marked_as_carried(tmp_path):
    """Three rows, then the guidance row alone with another sampling seed: the table keeps base and geometry (as
    recorded, each marked carried over, named by a note line) and replaces guidance by the re-run one; a full
    re-run carries nothing."""
    run_ablation(spec(tmp_path), FakeCommands())
    before = {r["variant"]: r for r in read_csv(tmp_path / "abl" / "ablation.csv")}
    commands = FakeCommands()
    subset = run_ablation(spec(tmp_path, variants=("guidance",), sample=["seed=5"]), commands)
    assert subset.ok, subset.errors
    assert commands.calls == [("sample", "guidance", "false"), ("evaluate", "guidance", "false")]  # only it, redone
    rows = read_csv(tmp_path / "abl" / "ablation.csv")
    assert [r["variant"] for r in rows] == ["base", "geometry", "guidance"] == [r["variant"] for r in subset.records]
    for r in rows[:2]:
        assert r["carried_from"] and {k: v for k, v in r.items() if k != "carried_from"} == \
            {k: v for k, v in before[r["variant"]].items() if k != "carried_from"}
    assert rows[2]["carried_from"] is None  # the re-run row replaced the recorded one
    md = (tmp_path / "abl" / "ablation.md").read_text()
    note = next(line for line in md.splitlines() if line.startswith("Rows carried over"))
    assert "Ours (base)" in note and "+Geometry" in note and "+Guidance" not in note
    full = run_ablation(spec(tmp_path), FakeCommands())
    assert not any(r.get("carried_from") for r in full.records) and "carried over" not in \
        (tmp_path / "abl" / "ablation.md").read_text()


@pytest.mark.slow  # four real rows and the console script (~33 s); the carried-rows rule is in make test with fakes
def test_spread_ablate_rerun_with_two_of_six_rows_keeps_six_rows(tiny_ablation):
    """The tiny ablation grown to the six rows (2 guidance iterations: the guidance row is redone), then
    `spread-ablate 'variants=[base,guidance]'` on the same folder (the console script): the table keeps six
    rows with the same numbers, four marked carried over (a carried row keeps its figure). Runs last on the
    module's tiny ablation (its folder gains the one-term rows)."""
    import ray

    from spread.commands.ablate import ablate as run
    from spread.experiments.ablation import VARIANTS

    six = [v for v in VARIANTS if v != "base_time"]  # conf/ablate.yaml's rows (base_time only on request)
    cfg, out = tiny_ablation["cfg"].copy(), tiny_ablation["out"]
    cfg.variants, cfg.figures = six, False
    cfg.sample.guidance = [*cfg.sample.guidance, "guidance.iterations=2"]
    cfg.stages.max_concurrent = 1  # the new rows in this process, their evaluations on one Ray session
    started = time.perf_counter()
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        grown_result = run(cfg)
    finally:
        ray.shutdown()
    assert grown_result.ok, grown_result.errors
    grown = time.perf_counter() - started
    before = read_csv(out / "ablation.csv")
    assert [r["variant"] for r in before] == six

    def listed(key: str) -> str:
        return f"{key}=[" + ",".join(f'"{x}"' for x in cfg[key.split(".")[0]][key.split(".")[1]]) + "]"

    started = time.perf_counter()
    proc = run_script("spread-ablate", "+preset=quick", f"data.root={tiny_ablation['data']}", f"out_dir={out}",
                      "variants=[base,guidance]", "logger=none", listed("train.extra"), listed("sample.extra"),
                      listed("sample.guidance"), listed("evaluate.extra"))
    rerun = time.perf_counter() - started
    rows = read_csv(out / "ablation.csv")
    assert [r["variant"] for r in rows] == six, proc.stdout[-3000:]
    carried = [r["variant"] for r in rows if r["carried_from"]]
    assert carried == ["geometry", "guidance_collision", "guidance_gravity", "guidance_relation"]
    strip = lambda r: {k: v for k, v in r.items() if k != "carried_from"}  # noqa: E731
    assert [strip(r) for r in rows] == [strip(r) for r in before]  # the same numbers, nothing re-run
    md = (out / "ablation.md").read_text()
    assert "Rows carried over from an earlier run" in md and "+Guidance (relation only) (evaluated" in md
    assert "Rows carried over from an earlier run" in proc.stdout  # and on the console, under the six rows
    assert "(ablation_geometry.png)" in md and "(ablation_guidance.png)" in md  # a carried row keeps its figure
    ledger = json.loads((out / "ablation.json").read_text())["stages"]
    assert [r["variant"] for r in ledger["table"]["inputs"]["rows"]] == six
    print(f"six rows grown in {grown:.1f} s ({ {k: v['seconds'] for k, v in ledger.items()} }); "
          f"spread-ablate re-run with two of six rows: {rerun:.1f} s")
