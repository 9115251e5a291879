"""spread-ablate: rows with one guidance term at a time, training seeds (mean ± sd across seeds beside the
bootstrap interval, error bars), training stages through a launcher (DDP inside an ablation).

Fast: the one-term rows' overrides and the table across seeds with fake commands (known answers); the
launchers' command lines. Slow: ``seeds=[0,1]`` with every row end to end on tiny data; a training stage as
2 CPU DDP processes (gloo) through ``train.launcher=local``.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pytest

from spread.experiments.ablation import Ablation, AblationSpec, TERMS, run_ablation
from spread.experiments.ablation_seeds import aggregate, run_seeded_ablation
from spread.commands.launch import LaunchedCommands, launch_prefix
from spread.reporting.tables import read_csv

from helpers import FAST_TRAIN, SMALL_MODEL, compose, make_dataset
from test_ablate_report import FakeCommands, args, metrics_json

ALL = ("base", "geometry", "guidance", *TERMS)


class SeededFakeCommands(FakeCommands):
    """FakeCommands whose Col_mesh depends on the row and the seed: 0.1 · row index + 0.01 · seed."""

    def evaluate(self, overrides):
        a = args(overrides)
        out = Path(a["out_dir"])
        out.mkdir(parents=True, exist_ok=True)
        value = 0.1 * ALL.index(out.name) + 0.01 * int(a["seed"])
        m = {**metrics_json(value, 1 - value), "col_mesh_lo": value - 0.05, "col_mesh_hi": value + 0.05,
             "bootstrap": {"level": 0.95, "resamples": 1000, "seed": 0, "method": "percentile"}}
        (out / "metrics.json").write_text(json.dumps(m))
        self.calls.append(("evaluate", out.name, a["resume"]))
        return {}


def fake_spec(tmp_path, **kw) -> AblationSpec:
    return AblationSpec(**{**dict(out_dir=tmp_path / "abl", train=["seed=0"], sample=["seed=0"],
                                  guidance=["guidance=refine", "guidance.gravity=4.0e-3"], evaluate=["seed=0"],
                                  generate=["rooms=4"], figures=False, variants=ALL), **kw})


def test_one_term_rows_keep_only_their_term(tmp_path):
    ablation = Ablation(fake_spec(tmp_path), FakeCommands())
    assert ablation.sample_lists("guidance") == ["seed=0", "guidance=refine", "guidance.gravity=4.0e-3"]
    assert ablation.sample_lists("guidance_collision")[-2:] == ["guidance.gravity=0.0", "guidance.relation=0.0"]
    assert ablation.sample_lists("guidance_gravity")[-3:] == ["guidance.gravity=4.0e-3", "guidance.collision=0.0",
                                                              "guidance.relation=0.0"]
    assert ablation.sample_lists("guidance_relation")[-2:] == ["guidance.collision=0.0", "guidance.gravity=0.0"]
    assert ablation.sample_lists("base") == ["seed=0"]


def test_one_term_rows_keep_the_stand_ins_of_their_term_and_zero_the_others(tmp_path):
    """The recipe's guidance may close gravity gaps with ``settle`` (gravity 0): the gravity row keeps it, the
    collision and relation rows zero it, and a plugin term named in the list is zeroed in every one-term row."""
    from spread.configs import compose, to_object

    guidance = ["guidance=refine", "guidance.gravity=0.0", "+guidance.terms.settle=0.3", "+guidance.terms.over=0.05",
                "+guidance.terms.home=0.01", "+guidance.terms.box_iou=0.1"]
    ablation = Ablation(fake_spec(tmp_path, guidance=guidance), FakeCommands())
    weights = {}
    for row in ("guidance", "guidance_collision", "guidance_gravity", "guidance_relation"):
        cfg = to_object(compose("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o", *ablation.sample_lists(row)[1:]]))
        weights[row] = cfg.guidance.weights(nonzero=True)
    assert weights["guidance"] == {"collision": 7.5e-3, "relation": 1e-3, "box_iou": 0.1, "settle": 0.3, "over": 0.05,
                                   "home": 0.01}
    assert weights["guidance_collision"] == {"collision": 7.5e-3}
    assert weights["guidance_gravity"] == {"settle": 0.3}
    assert weights["guidance_relation"] == {"relation": 1e-3, "over": 0.05, "home": 0.01}


def test_one_term_rows_ask_the_composed_guidance_which_terms_it_weighs_however_the_list_spells_them(tmp_path):
    """A term weighed by a preset (physcene's box_iou: no ``guidance.terms.<name>=`` string to read), one added and
    one added then turned off: the rows zero what the composed guidance weighs, and nothing it does not."""
    from spread.configs import compose, to_object

    guidance = ["guidance=physcene", "guidance.collision=7.5e-3", "+guidance.terms.settle=0.3",
                "+guidance.terms.over=0.05", "guidance.terms.over=0.0"]
    ablation = Ablation(fake_spec(tmp_path, guidance=guidance), FakeCommands())
    assert sorted(ablation.guidance_terms()) == ["box_iou", "settle"]
    weights = {}
    for row in ("guidance", "guidance_collision", "guidance_gravity"):
        cfg = to_object(compose("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o", *ablation.sample_lists(row)[1:]]))
        weights[row] = cfg.guidance.weights(nonzero=True)
    assert weights["guidance"] == {"collision": 7.5e-3, "box_iou": 0.15, "settle": 0.3}
    assert weights["guidance_collision"] == {"collision": 7.5e-3}
    assert weights["guidance_gravity"] == {"settle": 0.3}
    assert set(ablation.sample_lists("guidance_collision")[1 + len(guidance):]) == {  # over is weighed 0: not named
        "guidance.gravity=0.0", "guidance.relation=0.0", "++guidance.terms.box_iou=0.0", "++guidance.terms.settle=0.0"}


def test_seeds_table_is_mean_and_sd_across_seeds_beside_the_bootstrap(tmp_path):
    commands = SeededFakeCommands()
    result = run_seeded_ablation(fake_spec(tmp_path), commands, [0, 1, 2])
    assert not result.errors, result.errors
    assert [r["variant"] for r in result.records] == list(ALL)
    trains = [c for c in commands.calls if c[0] == "train"]
    assert len(trains) == 6 and [c for c in commands.calls if c[0] == "generate"] == [commands.calls[0]]  # data once
    for i, row in enumerate(result.records):
        assert row["seeds"] == 3 and math.isclose(row["col_mesh"], 0.1 * i + 0.01)  # mean of +0, +0.01, +0.02
        assert math.isclose(row["col_mesh_sd"], 0.01)  # sample sd of (0, 0.01, 0.02)
        assert math.isclose(row["col_mesh_hi"] - row["col_mesh_lo"], 0.1)
    md = (tmp_path / "abl" / "ablation.md").read_text()
    assert "+Guidance (gravity only)" in md and "0.410 ± 0.010 (± 0.050)" in md and "mean ± sd across 3" in md
    csv = read_csv(tmp_path / "abl" / "ablation.csv")
    assert csv[5]["variant"] == "guidance_relation" and math.isclose(csv[5]["col_mesh_sd"], 0.01)
    for seed in (0, 1, 2):
        assert (tmp_path / "abl" / f"seed{seed}" / "ablation.csv").exists()
        assert json.loads((tmp_path / "abl" / f"seed{seed}" / "ablation.json").read_text())["stages"]
    commands.calls.clear()  # resumed: every seed's stages are finished
    run_seeded_ablation(fake_spec(tmp_path), commands, [0, 1, 2])
    assert commands.calls == []


def test_every_seeds_equal_time_row_trains_after_its_base_and_geometry(tmp_path):
    commands = FakeCommands()
    result = run_seeded_ablation(fake_spec(tmp_path, variants=("base", "base_time", "geometry")), commands, [0, 1])
    assert not result.errors, result.errors
    trained = [Path(c[1]).name if "/" in c[1] else c[1] for c in commands.calls if c[0] == "train"]
    assert sorted(trained[:4]) == ["base", "base", "geometry", "geometry"] and trained[4:] == ["base_time"] * 2
    assert commands.trained["base_time"]["trainer.max_steps"] == "270"  # 100 geometry steps of 0.27 s, base 0.1 s
    assert [r["variant"] for r in result.records] == ["base", "base_time", "geometry"]


def test_error_bars_are_the_sd_across_seeds_else_the_bootstrap(tmp_path):
    from spread.reporting.plots import ablation_bars
    from spread.reporting.tables import metric_columns

    METRICS = metric_columns()

    rows = aggregate({0: [{"variant": "base", "status": "ok", "grecall": 0.5, "grecall_lo": 0.4, "grecall_hi": 0.7}],
                      1: [{"variant": "base", "status": "ok", "grecall": 0.7, "grecall_lo": 0.6, "grecall_hi": 0.8}]})
    drawn = ablation_bars(rows, METRICS[:1], tmp_path / "a.png", label_key="method")
    assert math.isclose(drawn["grecall"][0], 0.6) and math.isclose(drawn["grecall:error"][0][0], math.sqrt(0.02))
    boot = ablation_bars([{"method": "x", "grecall": 0.5, "grecall_lo": 0.4, "grecall_hi": 0.7}], METRICS[:1],
                         tmp_path / "b.png", label_key="method")
    assert [round(e, 6) for e in boot["grecall:error"][0]] == [0.1, 0.2]


def test_launchers_command_lines(monkeypatch):
    assert launch_prefix("local") == [sys.executable, "-m", "spread.cli.train"]
    torchrun = launch_prefix("torchrun", 2)
    assert torchrun[0].endswith("torchrun") and "--standalone" in torchrun and "--nproc-per-node=2" in torchrun
    monkeypatch.setenv("RDZV_ENDPOINT", "node0:29400")
    monkeypatch.setenv("RUN_ID", "job7")
    assert "--rdzv-id=job7" in launch_prefix("torchrun", 4, 2) and "--nnodes=2" in launch_prefix("torchrun", 4, 2)
    assert launch_prefix("srun", 4, 2)[:3] == ["srun", "--nodes=2", "--ntasks-per-node=4"]
    with pytest.raises(ValueError, match="train.launcher=mpirun"):
        LaunchedCommands("mpirun")


# ---- slow: end to end -------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return make_dataset(tmp_path_factory.mktemp("seedsdata"))


def tiny_cfg(data: Path, out: Path, *more: str):
    cfg = compose("ablate", "+preset=quick", f"data.root={data}", f"out_dir={out}", "figures=false", *more)
    cfg.train.extra = [*SMALL_MODEL, *FAST_TRAIN, "trainer.max_steps=2", "trainer.max_time=null",
                       *cfg.train.extra]
    cfg.sample.extra = ["sampler.steps=4", "progress=false", "renders=0", "figures=0", "batch_size=2",
                        "guidance.iterations=2"]
    cfg.evaluate.extra = ["protocol.stability_runs=1", "fid.enabled=false", "renders=0", "progress=false"]
    return cfg


@pytest.mark.slow
def test_two_seeds_with_every_row_end_to_end(data, tmp_path):
    from spread.commands.ablate import ablate

    result = ablate(tiny_cfg(data, tmp_path / "q", "seeds=[0,1]", f"variants=[{','.join(ALL)}]"))
    assert result.ok, result.errors
    assert [r["variant"] for r in result.records] == list(ALL)
    for r in result.records:
        assert r["seeds"] == 2 and r["col_mesh_sd"] is not None and r["grecall_lo"] <= r["grecall_hi"]
    seeds = [json.loads((tmp_path / "q" / f"seed{s}" / "samples" / "guidance_gravity" / "sampling.json").read_text())
             for s in (0, 1)]
    assert [m["fingerprint"]["sampling"]["seed"] for m in seeds] == [0, 1]
    assert "collision" not in seeds[0]["guidance"] and seeds[0]["guidance"]["gravity"] == 4.0e-3  # only it acts
    assert " ± " in (tmp_path / "q" / "ablation.md").read_text()


@pytest.mark.slow
def test_ddp_training_stage_inside_an_ablation(data, tmp_path):
    """train.launcher=local with trainer=ddp on 2 CPU processes (gloo): the stage completes, rank 0 writes."""
    from spread.commands.ablate import ablate

    cfg = tiny_cfg(data, tmp_path / "ddp", "variants=[geometry]", "train.launcher=local")
    cfg.train.extra = [*cfg.train.extra, "trainer=ddp", "trainer.accelerator=cpu", "trainer.devices=2"]
    result = ablate(cfg)
    assert result.ok, result.errors
    log = (tmp_path / "ddp" / "train" / "geometry" / "launch.log").read_text()
    assert "spread.cli.train" in log and "trainer=ddp" in log
    summary = json.loads((tmp_path / "ddp" / "train" / "geometry" / "metrics.json").read_text())
    assert summary["run"]["world_size"] == 2 and "git_sha" in summary["run"]
    assert result.records[0]["n_scenes"] == 3


# ---- concurrent rows -----------------------------------------------------------------------------------------

class SlowFakeCommands(SeededFakeCommands):
    """SeededFakeCommands whose sampling takes ``seconds`` (so that concurrent rows visibly overlap); with
    ``rendezvous`` (a folder) a sampling stage also waits, up to a minute, until a second one has started, so two
    stages that run at the same time overlap whatever the machine's load (one after the other, they do not)."""

    seconds = 2.5

    def __init__(self, rendezvous: Path | None = None):
        super().__init__()
        self.rendezvous = rendezvous

    def sample(self, overrides):
        import time

        if self.rendezvous is not None:
            self.rendezvous.mkdir(parents=True, exist_ok=True)
            (self.rendezvous / Path(args(overrides)["out_dir"]).name).touch()
            deadline = time.time() + 60
            while len(list(self.rendezvous.iterdir())) < 2 and time.time() < deadline:
                time.sleep(0.1)
        time.sleep(self.seconds)
        super().sample(overrides)


@pytest.mark.slow  # long (≥ 40 s on 2 cores): make test-slow runs it
def test_rows_run_concurrently_through_ray_and_give_the_sequential_table(tmp_path):
    """max_concurrent=2: two rows' stages overlap in time (ledger timestamps), each stage's record is the
    driver's ledger, and the table is the one a sequential run writes; a re-run re-uses every stage. Sampling
    on Ray actors (workers > 0) is one row at a time (two could each hold half the CPUs and wait for the rest)."""
    import ray
    from ray import cloudpickle

    from spread.experiments.ablation import run_ablation
    from spread.experiments.stage_pool import overlap
    from spread.runtime.ray import RaySettings

    import test_ablate_report

    for module in (sys.modules[__name__], test_ablate_report):  # the fakes travel to the Ray workers by value
        cloudpickle.register_pickle_by_value(module)
    rows = dict(variants=("base", "geometry", "guidance"), sample=["seed=0", "workers=0"])
    sequential = run_ablation(fake_spec(tmp_path / "seq", **rows), SlowFakeCommands())
    settings = RaySettings(num_cpus=2)
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)  # one session, used as is
    try:
        concurrent = run_ablation(fake_spec(tmp_path / "par", max_concurrent=2, ray=settings, **rows),
                                  SlowFakeCommands(rendezvous=tmp_path / "started"))
        again = run_ablation(fake_spec(tmp_path / "par", max_concurrent=2, ray=settings, **rows), SlowFakeCommands())
        actors = run_ablation(fake_spec(tmp_path / "actors", max_concurrent=2, ray=settings,
                                        **{**rows, "sample": ["seed=0", "workers=2"]}), SlowFakeCommands())
    finally:
        ray.shutdown()
    assert sequential.ok and concurrent.ok, concurrent.errors
    assert set(concurrent.stages.values()) == {"done"}
    stages = json.loads((tmp_path / "par" / "abl" / "ablation.json").read_text())["stages"]
    assert overlap(stages, "sample/base", "sample/geometry") > 0, "the first two rows ran at the same time"
    assert overlap(stages, "sample/base", "evaluate/base") == 0, "a row's evaluation waits for its samples"
    seq_stages = json.loads((tmp_path / "seq" / "abl" / "ablation.json").read_text())["stages"]
    assert overlap(seq_stages, "sample/base", "sample/geometry") == 0
    assert set(stages) == set(seq_stages)
    assert read_csv(tmp_path / "par" / "abl" / "ablation.csv") == read_csv(tmp_path / "seq" / "abl" / "ablation.csv")
    assert (tmp_path / "par" / "abl" / "ablation.md").read_text() == (tmp_path / "seq" / "abl" / "ablation.md").read_text()
    assert set(again.stages.values()) == {"skipped"}
    assert actors.ok, actors.errors
    stages = json.loads((tmp_path / "actors" / "abl" / "ablation.json").read_text())["stages"]
    assert all(overlap(stages, f"sample/{a}", f"sample/{b}") == 0
               for a, b in [("base", "geometry"), ("base", "guidance"), ("geometry", "guidance")])
    assert read_csv(tmp_path / "actors" / "abl" / "ablation.csv") == read_csv(tmp_path / "seq" / "abl" / "ablation.csv")


# ---- concurrent training stages (issue 31, item 7) ---------------------------------------------------------------

class SlowTrainFakeCommands(SeededFakeCommands):
    """SeededFakeCommands whose training takes ``seconds``; with ``rendezvous`` (a folder) a training stage also
    waits, up to a minute, until a second one has started (so two that run at the same time overlap whatever the
    machine's load)."""

    seconds = 1.5

    def __init__(self, rendezvous: Path | None = None):
        super().__init__()
        self.rendezvous = rendezvous

    def train(self, overrides, run_dir):
        import time

        if self.rendezvous is not None:
            self.rendezvous.mkdir(parents=True, exist_ok=True)
            (self.rendezvous / f"{run_dir.parent.parent.name}_{run_dir.name}").touch()
            deadline = time.time() + 60
            while len(list(self.rendezvous.iterdir())) < 2 and time.time() < deadline:
                time.sleep(0.1)
        time.sleep(self.seconds)
        super().train(overrides, run_dir)


def training_entries(out: Path, seeds=(0, 1)) -> dict[str, dict]:
    """``seed<k>/train/<t>`` → its ledger entry."""
    return {f"seed{s}/{name}": entry for s in seeds
            for name, entry in json.loads((out / f"seed{s}" / "ablation.json").read_text())["stages"].items()
            if name.startswith("train/")}


def most_at_once(entries: dict[str, dict]) -> int:
    """The most ledger entries whose [started_at, ended_at) intervals hold one moment."""
    return max(sum(e["started_at"] <= x["started_at"] < e["ended_at"] for e in entries.values())
               for x in entries.values())


@pytest.mark.slow  # make test-slow (kept out of make test's 15 minutes)
def test_training_stages_run_two_at_a_time_and_give_the_sequential_table(tmp_path):
    """3 rows × 2 seeds (4 training stages: base and geometry per seed) with ``train_concurrent=2``: the ledger's
    times show two training stages at once and never three, each recorded in its seed's ledger, and the table
    across seeds is the sequential run's; a GPU asked of a cluster without one fails the stage (no wait for
    ever); ``stages.train_*`` reach the spec from conf/ablate.yaml."""
    import ray
    from ray import cloudpickle

    from spread.commands.ablate import ablation_spec
    from spread.experiments.stage_pool import overlap
    from spread.runtime.ray import RaySettings

    import test_ablate_report

    for module in (sys.modules[__name__], test_ablate_report):  # the fakes travel to the Ray workers by value
        cloudpickle.register_pickle_by_value(module)
    rows = dict(variants=("base", "geometry", "guidance"))
    sequential = run_seeded_ablation(fake_spec(tmp_path / "seq", **rows), SlowTrainFakeCommands(), [0, 1])
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)  # one session, used as is
    try:
        concurrent = run_seeded_ablation(fake_spec(tmp_path / "par", train_concurrent=2, ray=RaySettings(num_cpus=2),
                                                   **rows), SlowTrainFakeCommands(tmp_path / "started"), [0, 1])
        no_gpu = run_ablation(fake_spec(tmp_path / "gpu", train_concurrent=2, train_gpus=1, **rows), FakeCommands())
    finally:
        ray.shutdown()
    assert sequential.ok and concurrent.ok, concurrent.errors
    entries, seq_entries = training_entries(tmp_path / "par" / "abl"), training_entries(tmp_path / "seq" / "abl")
    assert sorted(entries) == sorted(seq_entries) == ["seed0/train/base", "seed0/train/geometry",
                                                      "seed1/train/base", "seed1/train/geometry"]
    assert overlap(entries, "seed0/train/base", "seed0/train/geometry") > 0, "the first two trained at once"
    assert most_at_once(entries) == 2 and most_at_once(seq_entries) == 1
    assert read_csv(tmp_path / "par" / "abl" / "ablation.csv") == read_csv(tmp_path / "seq" / "abl" / "ablation.csv")
    # a training stage that asks for more than the cluster has fails, named, instead of waiting for ever
    assert no_gpu.stages["train/base"] == "failed" and "1 GPU" in no_gpu.errors["train/base"]
    assert no_gpu.stages["sample/guidance"] == "blocked"
    spec = ablation_spec(compose("ablate", "+preset=quick", "stages.train_concurrent=6", "stages.train_gpus=1"))
    assert (spec.train_concurrent, spec.train_cpus, spec.train_gpus) == (6, 1.0, 1.0)
    assert ablation_spec(compose("ablate", "+preset=quick")).train_concurrent == 1  # default: one after another


@pytest.mark.slow
def test_real_training_stages_two_at_a_time_give_the_sequential_numbers(data, tmp_path):
    """The tiny recipe, 3 rows × 2 seeds, trained one after another and two at a time (Ray tasks of one CPU):
    the same checkpoints bit for bit and the same table across seeds."""
    import ray
    import torch

    from spread.commands.ablate import ablate

    more = ("seeds=[0,1]", "variants=[base,geometry,guidance]", "stages.max_concurrent=1", "logger=none")
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)  # shared by both runs
    try:
        sequential = ablate(tiny_cfg(data, tmp_path / "seq", *more))
        concurrent = ablate(tiny_cfg(data, tmp_path / "par", *more, "stages.train_concurrent=2"))
    finally:
        ray.shutdown()
    assert sequential.ok and concurrent.ok, (sequential.errors, concurrent.errors)
    entries = training_entries(tmp_path / "par")
    assert most_at_once(entries) == 2 and most_at_once(training_entries(tmp_path / "seq")) == 1
    for name in entries:
        a, b = (torch.load(tmp_path / run / name / "checkpoints" / "last.ckpt",
                           map_location="cpu", weights_only=False)["state_dict"] for run in ("seq", "par"))
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), f"{name} trained differently"
    assert read_csv(tmp_path / "par" / "ablation.csv") == read_csv(tmp_path / "seq" / "ablation.csv")
