"""``spread-sweep`` (spread.experiments.sweep) and the Hydra multirun sweep: no stale point, ever.

Fast: the command line → settings, fixed overrides and the search space (presets, comma lists, choice/range/
interval, Optuna); every ``spread-sweep`` line documented in conf/sweep_run.yaml parses; the results table.
Slow (a dataset, a tiny checkpoint, real sampling and evaluation): the documented Hydra multirun re-launched
with another ``guidance.iterations`` makes a new point and an identical re-launch re-uses it; ``spread-sweep``
with two points writes results.csv, re-uses both points on a re-run, and after a kill finishes with the same
table; Optuna search; a sweep over a two-node ``ray.cluster_utils.Cluster`` uses both nodes.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shlex
import signal
import subprocess
import time
from pathlib import Path

import pytest

from spread.configs import conf_dir
from spread.experiments.sweep import (
    SweepSettings, grid_points, mark_best, parse_arguments, read_results_csv, search_space, write_results,
)

from helpers import FAST_TRAIN, SCRIPTS, SMALL_MODEL, make_dataset, train_in_process

TWO = ["+sweep=guidance_grid", "guidance.collision=0.0,0.0075", "guidance.gravity=0.001", "guidance.relation=0.001"]
QUICK = ["guidance.iterations=2", "sampler.steps=4", "batch_size=2", "renders=0", "logger=none",
         "evaluation.protocol.stability_runs=1", "evaluation.fid.enabled=false"]
ENV = {**os.environ, "WANDB_MODE": "disabled", "HYDRA_FULL_ERROR": "1", "OMP_NUM_THREADS": "1"}


# ---- fast: the command line and the table ------------------------------------------------------------------

def test_preset_grid_and_command_line_lists_make_the_dimensions():
    plan = parse_arguments(["ckpt=c.ckpt", "data.root=/d", *TWO, "max_concurrent=2", "out_dir=/tmp/x"])
    assert plan.settings.max_concurrent == 2 and plan.settings.out_dir == "/tmp/x"
    assert [(d.key, d.values) for d in plan.dimensions] == [("guidance.collision", ["0.0", "0.0075"])]
    assert "guidance.gravity=0.001" in plan.fixed and "ckpt=c.ckpt" in plan.fixed and "evaluate=true" in plan.fixed
    assert grid_points(plan) == [{"guidance.collision": "0.0"}, {"guidance.collision": "0.0075"}]
    # the preset's other weights stay swept unless fixed: 2 × 3 × 3 points
    plan = parse_arguments(["ckpt=c", "data.root=/d", "+sweep=guidance_grid", "guidance.collision=0.0,0.0075",
                            "out_dir=/tmp/x"])
    assert {d.key: len(d.values) for d in plan.dimensions} == {"guidance.collision": 2, "guidance.gravity": 3,
                                                                "guidance.relation": 3}
    assert len(grid_points(plan)) == 18 and len(grid_points(parse_arguments(
        ["ckpt=c", "data.root=/d", "+sweep=guidance_grid", "out_dir=/x"]))) == 27


def test_hydra_search_syntax_becomes_tune_distributions():
    from ray.tune.search.sample import Categorical, Float

    plan = parse_arguments(["ckpt=c", "data.root=/d", "guidance=refine", "guidance.collision=interval(0.0,0.03)",
                            "guidance.gravity=choice(0.0,0.001)", "guidance.iterations=range(1,4)",
                            "search=optuna", "num_samples=3", "metric=col_mesh", "mode=min", "out_dir=/x"])
    space = search_space(plan)
    assert isinstance(space["guidance.collision"], Float) and space["guidance.collision"].lower == 0.0
    assert isinstance(space["guidance.gravity"], Categorical) and space["guidance.gravity"].categories == ["0.0", "0.001"]
    assert space["guidance.iterations"].categories == ["1", "2", "3"]
    with pytest.raises(ValueError, match=r"interval\(\) on \['guidance.collision'\] needs search=random"):
        parse_arguments(["ckpt=c", "data.root=/d", "guidance.collision=interval(0.0,0.03)", "out_dir=/x"])
    with pytest.raises(ValueError, match="out_dir is required"):
        parse_arguments(["ckpt=c", "data.root=/d"])
    with pytest.raises(ValueError, match="search=bayes: unknown sweep search 'bayes' .*grid, random, optuna"):
        SweepSettings(out_dir="/x", search="bayes")
    with pytest.raises(ValueError, match="scheduler=hyperband: unknown trial scheduler 'hyperband' .*asha"):
        SweepSettings(out_dir="/x", scheduler="hyperband")


def test_an_integer_interval_draws_whole_numbers_from_both_ends_and_a_real_one_for_a_count_is_refused_with_the_way(
        tmp_path):
    """``interval(2,4)`` draws reals: ``trainer.max_steps`` refused 2.0, ``data.batch_size=3.274`` trained batches of 3
    under its own name. Hydra's ``int(interval(2,4))`` draws 2, 3 or 4."""
    import random

    from ray.tune.search.sample import Integer

    from spread.experiments.sweep import checked_sweep

    plan = parse_arguments(["command=train", f"data.root={tmp_path}", "search=random", "num_samples=2",
                            "data.batch_size=int(interval(2,4))", "trainer.max_steps=tag(log,int(interval(1,8)))",
                            f"out_dir={tmp_path / 'x'}"])
    space = search_space(plan)
    assert isinstance(space["data.batch_size"], Integer) and isinstance(space["trainer.max_steps"], Integer)
    random.seed(0)
    draws = {space["data.batch_size"].sample(random_state=i) for i in range(60)}
    assert draws == {2, 3, 4} and all(type(v) is int for v in draws)
    for key in ("data.batch_size", "trainer.max_steps"):
        plan = parse_arguments(["command=train", f"data.root={tmp_path}", "search=random", "num_samples=2",
                                f"{key}=interval(2,4)", f"out_dir={tmp_path / 'x'}"])
        with pytest.raises(ValueError, match=rf"^{key}=2.0: .* write {key}='int\(interval\(2,4\)\)' to draw whole "):
            checked_sweep(plan)
    for interval, way in [("tag(log,interval(2,64))", r"write data.batch_size='tag\(log,int\(interval\(2,64\)\)\)'"),
                          ("interval(2.5,3.5)", "its one whole number is 3: write data.batch_size=3"),
                          ("interval(2.5,2.9)", "it holds no whole number")]:
        plan = parse_arguments(["command=train", f"data.root={tmp_path}", "search=random", "num_samples=2",
                                f"data.batch_size={interval}", f"out_dir={tmp_path / 'x'}"])
        with pytest.raises(ValueError, match=way):
            checked_sweep(plan)
    with pytest.raises(ValueError, match=r"int\(interval\(1.5,3.5\)\): int\(\) of an interval with the end 1.5"):
        parse_arguments(["command=train", "data.root=/d", "search=random", "data.batch_size=int(interval(1.5,3.5))",
                         "out_dir=/x"])  # Hydra truncated it to 1..3
    one = parse_arguments(["command=train", "data.root=/d", "search=random", "data.batch_size=int(interval(3,3))",
                           "out_dir=/x"])
    assert search_space(one)["data.batch_size"].sample() == 3
    assert not (tmp_path / "x").exists()


def test_searches_and_trial_schedulers_are_chosen_by_registered_name_or_target():
    """A search or a trial scheduler is a registry entry (a plugin adds one) or any Ray Tune class by
    ``module:Class``, built with the sweep's metric and mode."""
    from ray.tune.schedulers import MedianStoppingRule
    from ray.tune.search.optuna import OptunaSearch

    from spread.experiments.tuning import SEARCHES, SearchSpec, search_spec, trial_scheduler_spec

    settings = SweepSettings(out_dir="/x", search="ray.tune.search.optuna:OptunaSearch", metric="col_mesh", mode="min",
                             scheduler="ray.tune.schedulers:MedianStoppingRule")
    assert not settings.grid and isinstance(search_spec(settings.search).build(settings), OptunaSearch)
    scheduler = trial_scheduler_spec(settings.scheduler).build(settings)
    assert isinstance(scheduler, MedianStoppingRule) and scheduler._metric == "col_mesh"
    SEARCHES.register("every_other", SearchSpec("every_other", None, grid=True, description="a plugin's grid"))
    try:
        plan = parse_arguments(["ckpt=c", "data.root=/d", "guidance.collision=0.0,0.1", "search=every_other",
                                "out_dir=/x"])
        assert plan.settings.grid and len(grid_points(plan)) == 2
    finally:
        SEARCHES.unregister("every_other")
    with pytest.raises(ValueError, match="search=ray.tune.search:NoSuchSearch: .*AttributeError"):
        SweepSettings(out_dir="/x", search="ray.tune.search:NoSuchSearch")


def documented_lines(path: Path, command: str) -> list[list[str]]:
    text = path.read_text()
    lines = [line.split(command, 1)[1].split("  #")[0] for line in text.splitlines()
             if line.lstrip("# ").startswith(command + " ")]
    return [shlex.split(line.replace("CKPT", "c.ckpt").replace("DIR", "/d")) for line in lines]


def test_every_documented_spread_sweep_line_parses():
    lines = documented_lines(Path(conf_dir()) / "sweep_run.yaml", "spread-sweep") \
        + documented_lines(Path(conf_dir()) / "sweep" / "guidance_grid.yaml", "spread-sweep")
    assert len(lines) >= 6
    for args in lines:
        plan = parse_arguments(args)
        assert plan.dimensions, args


def test_results_table_marks_the_best_point_and_reads_back(tmp_path):
    plan = parse_arguments(["ckpt=c", "data.root=/d", *TWO, f"out_dir={tmp_path}", "metric=col_mesh", "mode=min"])
    rows = [{"guidance.collision": 0.0, "grecall": 0.5, "grecall_lo": 0.4, "grecall_hi": 0.6, "col_mesh": 0.3,
             "seconds": 2.0, "point": "a", "status": "ok"},
            {"guidance.collision": 0.0075, "grecall": 0.4, "col_mesh": 0.1, "seconds": 3.0, "point": "b", "status": "ok"}]
    best = mark_best(rows, "col_mesh", "min")
    assert best["point"] == "b"
    csv_path, md_path = write_results(rows, tmp_path, plan, best)
    back = read_results_csv(csv_path)
    assert [r["guidance.collision"] for r in back] == [0.0, 0.0075] and [r["best"] for r in back] == ["False", "True"]
    assert back[0]["grecall_lo"] == 0.4 and back[1]["grecall_lo"] is None
    md = md_path.read_text()
    assert "| ★ | 0.0075 |" in md and "0.500 ± 0.100" in md and "Best: b (Col_mesh = 0.100)" in md


def test_the_results_table_names_every_other_setting_that_differs_between_points(tmp_path):
    """Two points alike in the swept key but recorded with other refinement iterations (their point.json
    identities) are two rows, each naming its iterations; what every point shares is said once."""
    plan = parse_arguments(["ckpt=c", "data.root=/d", "guidance=refine", "guidance.collision=0.0075,0.015",
                            f"out_dir={tmp_path}"])
    settings = {"guidance.mode": "refine", "guidance.collision": 0.0075, "sampler": "ddim-4"}
    rows = [{"guidance.collision": 0.0075, "grecall": 0.5, "point": p, "status": "ok",
             "settings": {**settings, "guidance.iterations": n}} for p, n in (("a", 1), ("b", 2))]
    csv_path, md_path = write_results(rows, tmp_path, plan, mark_best(rows, "grecall", "max"))
    assert [(r["guidance.collision"], r["guidance.iterations"]) for r in read_results_csv(csv_path)] == [
        (0.0075, 1.0), (0.0075, 2.0)]
    md = md_path.read_text()
    assert "| guidance.collision | guidance.iterations |" in md and "Every point: guidance.mode=refine" in md
    assert "sampler=ddim-4" in md


def test_a_drawing_search_is_another_search_when_its_checkpoint_or_data_change_at_the_same_paths(tmp_path):
    """A resumed random or Optuna search would report its restored trials: new weights or rooms at the same paths
    are another search (its identity holds their content), not a resume."""
    import os

    from spread.experiments.sweep import search_identity

    ckpt, data = tmp_path / "m.ckpt", tmp_path / "data"
    ckpt.write_bytes(b"weights-1")
    (data / "test").mkdir(parents=True)
    (data / "test" / "a.npz").write_bytes(b"scene-a")
    plan = parse_arguments([f"ckpt={ckpt}", f"data.root={data}", "guidance=refine", "guidance.gravity=0.001",
                            "guidance.collision=interval(0.0,0.03)", *QUICK, "search=random", "num_samples=2",
                            f"out_dir={tmp_path / 'S'}"])
    shared = {"fixed": plan.fixed, "points": str(tmp_path / "S" / "points"), "name": plan.settings.name,
              "metric": plan.settings.metric, "scheduler": plan.settings.scheduler, "seeds": plan.settings.seeds,
              "cwd": os.getcwd()}
    first = search_identity(plan, shared)
    assert first == search_identity(plan, shared) and first["inputs"]["ckpt_sha256"]
    ckpt.write_bytes(b"weights-2")
    assert search_identity(plan, shared)["inputs"]["ckpt_sha256"] != first["inputs"]["ckpt_sha256"]
    ckpt.write_bytes(b"weights-1")
    (data / "test" / "a.npz").write_bytes(b"scene-a, rewritten")
    assert search_identity(plan, shared)["inputs"]["data"] != first["inputs"]["data"]


def test_seeds_give_one_csv_row_per_seed_and_one_table_line_per_point_with_its_interval_over_seeds(tmp_path):
    """``seeds=2``: results.csv keeps every seed's row (ASD in mm), results.md one line per point, each metric the
    mean over its seeds ± half the 95 % Student-t interval over them (t(0.975, 1) = 12.706), the best point by
    its mean."""
    from spread.experiments.sweep import seed_means

    plan = parse_arguments(["ckpt=c", "data.root=/d", *TWO, f"out_dir={tmp_path}", "seeds=2"])
    assert plan.settings.seeds == 2
    values = {(0.0, 0): 0.8, (0.0, 1): 0.9, (0.0075, 0): 0.7, (0.0075, 1): 0.7}
    rows = [{"guidance.collision": w, "seed": seed, "grecall": g, "asd": 0.012, "status": "ok",
             "point": f"collision{w}_seed{seed}_abc", "seconds": 1.0} for (w, seed), g in values.items()]
    points = seed_means(rows, plan)
    assert [p["point"] for p in points] == ["collision0.0", "collision0.0075"]
    first = points[0]
    half = 12.706 * (0.1 / 2 ** 0.5) / 2 ** 0.5
    assert first["grecall"] == pytest.approx(0.85) and first["grecall_sd"] == pytest.approx(0.1 / 2 ** 0.5)
    assert first["grecall_lo"] == pytest.approx(0.85 - half, abs=1e-3) and first["n_seeds"] == 2
    assert first["seeds"] == [0, 1] and points[1]["grecall_hi"] == pytest.approx(0.7)  # no spread: zero width
    drawn_twice = seed_means([*rows, *[dict(r) for r in rows[:2]]], plan)  # a random search repeating a point
    assert drawn_twice[0]["n_seeds"] == 2 and drawn_twice[0]["grecall_lo"] == pytest.approx(first["grecall_lo"])
    best = mark_best(points, "grecall", "max")
    for r in rows:
        r["best"] = r["guidance.collision"] == best["guidance.collision"]
    csv_path, md_path = write_results(rows, tmp_path, plan, best, points)
    back = read_results_csv(csv_path)
    assert [(r["guidance.collision"], r["seed"]) for r in back] == list(values)
    assert back[0]["asd_mm"] == pytest.approx(12.0) and [r["best"] for r in back] == ["True", "True", "False", "False"]
    md = md_path.read_text()
    assert md.count("| ★ |") == 1 and "0.850 ± 0.635" in md and "2 points" in md and "Student-t" in md
    with pytest.raises(ValueError, match="seeds=2 is for command=sample"):
        parse_arguments(["command=train", "data.root=/d", "model.lr=1e-3,1e-4", f"out_dir={tmp_path}", "seeds=2"])
    with pytest.raises(ValueError, match="seeds=0"):
        parse_arguments(["ckpt=c", "data.root=/d", *TWO, f"out_dir={tmp_path}", "seeds=0"])


# ---- slow: real points ---------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """12 generated rooms (3 test graphs) and a 2-step checkpoint of the shrunken model."""
    import torch

    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("sweepdata")
    data = make_dataset(root)
    train_in_process(root / "train", f"data.root={data}", "experiment=quick", *SMALL_MODEL, *FAST_TRAIN,
                     "trainer.max_steps=2", "trainer.max_time=null")
    return {"data": data, "ckpt": root / "train" / "checkpoints" / "last.ckpt"}


def spread(script: str, *args: str, timeout: int = 600) -> subprocess.CompletedProcess:
    proc = subprocess.run([str(SCRIPTS / script), *args], env=ENV, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


@pytest.mark.slow
def test_hydra_multirun_relaunch_redoes_a_changed_point_and_reuses_an_identical_one(tiny, tmp_path):
    sweep = tmp_path / "grid"
    args = ["-m", "+sweep=guidance_grid", f"ckpt={tiny['ckpt']}", f"data.root={tiny['data']}", f"sweep_dir={sweep}",
            "guidance.collision=0.0075", "guidance.gravity=0.001", "guidance.relation=0.001", *QUICK[1:],
            "workers=0", "progress=false", "ray.num_cpus=1"]
    spread("spread-sample", *args, "guidance.iterations=2")
    (first,) = sweep.glob("c0.0075_g0.001_r0.001_*")
    stamp = (first / "metrics.json").stat().st_mtime_ns
    again = spread("spread-sample", *args, "guidance.iterations=2")
    assert "finished earlier with the same fingerprint, re-used" in again.stdout + again.stderr
    assert (first / "metrics.json").stat().st_mtime_ns == stamp
    spread("spread-sample", *args, "guidance.iterations=3")
    points = sorted(sweep.glob("c0.0075_g0.001_r0.001_*"))
    assert len(points) == 2 and (first / "metrics.json").stat().st_mtime_ns == stamp
    (new,) = [p for p in points if p != first]
    record = json.loads((new / "point.json").read_text())
    assert record["status"] == "finished" and record["fingerprint"]["guidance"]["iterations"] == 3
    assert json.loads((new / "metrics.json").read_text())["n_scenes"] == 3
    launches = sorted((sweep / ".launches").iterdir())
    assert len(launches) == 3 and all((launch / "multirun.yaml").exists() for launch in launches)


def sweep_args(tiny, out: Path, *more: str) -> list[str]:
    return [f"ckpt={tiny['ckpt']}", f"data.root={tiny['data']}", *TWO, *QUICK, "num_cpus=2", f"out_dir={out}", *more]


def table(path: Path) -> list[dict]:
    keep = re.compile(r"^(guidance\.|col_mesh|grecall|asd|stability|still_fraction|point$|best$|n_scenes)")
    return [{k: v for k, v in r.items() if keep.match(k)} for r in read_results_csv(path)]


@pytest.mark.slow
def test_spread_sweep_two_points_reuse_and_resume_after_a_kill(tiny, tmp_path):
    out = tmp_path / "D"
    started = time.perf_counter()
    spread("spread-sweep", *sweep_args(tiny, out, "max_concurrent=2"))
    first = time.perf_counter() - started
    rows = read_results_csv(out / "results.csv")
    assert [r["guidance.collision"] for r in rows] == [0.0, 0.0075] and "grecall" in rows[0]
    assert all(r["status"] == "ok" and r["n_scenes"] == 3 and r["grecall_lo"] <= r["grecall"] <= r["grecall_hi"]
               for r in rows)
    assert sum(r["best"] == "True" for r in rows) == 1 and "★" in (out / "results.md").read_text()
    started = time.perf_counter()
    again = spread("spread-sweep", *sweep_args(tiny, out, "max_concurrent=2"))
    assert time.perf_counter() - started < 0.6 * first, again.stdout[-2000:]
    assert all(r["reused"] == "True" for r in read_results_csv(out / "results.csv"))
    assert table(out / "results.csv") == table(out / "results.csv")
    # killed after its first point, then run again: the same table as the uninterrupted sweep
    killed = tmp_path / "K"
    log = open(tmp_path / "killed.log", "w")
    proc = subprocess.Popen([str(SCRIPTS / "spread-sweep"), *sweep_args(tiny, killed, "max_concurrent=1")], env=ENV,
                            stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.time() + 400
        while time.time() < deadline and proc.poll() is None and not any(
                json.loads(p.read_text()).get("status") == "finished" for p in killed.glob("points/*/point.json")):
            time.sleep(0.2)
        os.kill(proc.pid, signal.SIGKILL)  # the driver alone, as `kill -9 <pid>`: its Ray processes stay
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not (killed / "results.csv").exists()
    record = json.loads((killed / ".ray-session.json").read_text())
    from spread.runtime.ray import leftover_processes

    left = leftover_processes(record)
    assert left, "the killed driver's raylet and GCS are still running"
    spread("spread-sweep", *sweep_args(tiny, killed, "max_concurrent=1"))
    assert table(killed / "results.csv") == table(out / "results.csv")
    assert not [p for p in left if os.path.exists(f"/proc/{p}") and record["session_dir"] in
                open(f"/proc/{p}/cmdline").read()], "the relaunch stopped every process of the killed run"
    assert not (killed / ".ray-session.json").exists()
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)


def wait_for_finished_point(proc, folder: Path, timeout: float = 400) -> None:
    deadline = time.time() + timeout
    while time.time() < deadline and proc.poll() is None and not any(
            json.loads(p.read_text()).get("status") == "finished" for p in folder.glob("points/*/point.json")):
        time.sleep(0.2)


@pytest.mark.slow
def test_an_interrupted_optuna_sweep_resumes_with_the_same_suggestions(tiny, tmp_path):
    """Killed (``kill -9``) after its first finished trial, the re-launched Optuna sweep restores its searcher and
    trials from Ray Tune's state and ends with the uninterrupted sweep's points; a changed search starts afresh."""
    args = [f"ckpt={tiny['ckpt']}", f"data.root={tiny['data']}", "guidance=refine", "guidance.gravity=0.001",
            "guidance.collision=interval(0.0,0.03)", *QUICK, "search=optuna", "num_samples=3", "max_concurrent=1",
            "num_cpus=2", "metric=col_mesh", "mode=min"]
    spread("spread-sweep", *args, f"out_dir={tmp_path / 'whole'}")
    whole = sorted(r["guidance.collision"] for r in read_results_csv(tmp_path / "whole" / "results.csv"))
    killed = tmp_path / "killed"
    with open(tmp_path / "killed.log", "w") as log:
        proc = subprocess.Popen([str(SCRIPTS / "spread-sweep"), *args, f"out_dir={killed}"], env=ENV, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
        try:
            wait_for_finished_point(proc, killed)
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
    assert not (killed / "results.csv").exists()
    again = spread("spread-sweep", *args, f"out_dir={killed}")
    assert "resuming the search" in again.stdout + again.stderr
    rows = read_results_csv(killed / "results.csv")
    assert len(rows) == 3 and sorted(r["guidance.collision"] for r in rows) == whole
    assert all(len(str(r["guidance.collision"]).split(".")[-1]) <= 6 for r in rows)  # 4 significant digits
    other = spread("spread-sweep", *[a.replace("num_samples=3", "num_samples=4") for a in args], f"out_dir={killed}")
    assert "resuming the search" not in other.stdout + other.stderr
    assert len(read_results_csv(killed / "results.csv")) == 4 and len(list((killed / "tune").glob("sweep.*"))) == 1
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)


@pytest.mark.slow
def test_a_sweep_with_two_seeds_reports_intervals_over_seeds_and_a_paired_difference(tiny, tmp_path):
    """``seeds=2``: each of two points sampled with seeds 0 and 1 (four folders), results.csv a row per seed,
    results.md one line per point with its interval over the seeds; ``spread.results`` gives the paired difference
    of the two points on the same graphs and seeds."""
    from spread import results

    out = tmp_path / "S"
    spread("spread-sweep", *sweep_args(tiny, out, "max_concurrent=2", "seeds=2", "seed=0"))
    rows = read_results_csv(out / "results.csv")
    assert [(r["guidance.collision"], r["seed"]) for r in rows] == [(0.0, 0.0), (0.0, 1.0), (0.0075, 0.0),
                                                                   (0.0075, 1.0)]
    assert len({r["point"] for r in rows}) == 4 and all("_seed" in r["point"] for r in rows)
    md = (out / "results.md").read_text()
    assert "2 points" in md and "Student-t interval over those seeds" in md and md.count("| ★ |") == 1
    folders = {w: [out / "points" / r["point"] for r in rows if r["guidance.collision"] == w] for w in (0.0, 0.0075)}
    diff = results.paired_difference(folders[0.0075], folders[0.0], "grecall", resamples=200, seed=0)
    assert diff["n_pairs"] == 2 * 3 and diff["lo"] <= diff["diff"] <= diff["hi"]
    frame = results.load(out)
    assert {"guidance.collision", "seed", "grecall"} <= set(frame.columns) and len(frame) == 4


@pytest.mark.slow
def test_optuna_search_and_a_two_node_cluster(tiny, tmp_path):
    """Optuna TPE over an interval on a 2-node ray.cluster_utils.Cluster (one CPU each): both nodes run trials."""
    from ray.cluster_utils import Cluster

    from spread.commands.in_process import InProcessCommands
    from spread.experiments.sweep import run_sweep

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    cluster.add_node(num_cpus=1)
    cluster.wait_for_nodes()
    try:
        plan = parse_arguments([f"ckpt={tiny['ckpt']}", f"data.root={tiny['data']}", "guidance=refine",
                                "guidance.collision=interval(0.0,0.03)", "guidance.gravity=0.001", *QUICK,
                                "search=optuna", "num_samples=4", "max_concurrent=2", f"address={cluster.address}",
                                f"out_dir={tmp_path / 'tpe'}", "metric=col_mesh", "mode=min"])
        result = run_sweep(plan, InProcessCommands())
    finally:
        import ray

        ray.shutdown()
        cluster.shutdown()
    assert len(result.rows) == 4 and all(r["status"] == "ok" for r in result.rows)
    assert all(0.0 <= r["guidance.collision"] <= 0.03 for r in result.rows)
    assert len({r["node"] for r in result.rows}) == 2
    assert result.best is not None and result.best["col_mesh"] == min(r["col_mesh"] for r in result.rows)


@pytest.mark.slow
def test_training_sweep_with_asha_reports_each_validation(tiny, tmp_path):
    from spread.commands.in_process import InProcessCommands
    from spread.experiments.sweep import run_sweep

    plan = parse_arguments(["command=train", "experiment=quick", f"data.root={tiny['data']}", *SMALL_MODEL,
                            *FAST_TRAIN, "trainer.max_steps=4", "trainer.max_time=null",
                            "trainer.check_val_every_n_epoch=1", "model.lr=1e-3,5e-4", "scheduler=asha",
                            "metric=val/loss", "mode=min", "num_cpus=2", "max_concurrent=2", f"out_dir={tmp_path / 'lr'}"])
    result = run_sweep(plan, InProcessCommands())
    assert [r["model.lr"] for r in result.rows] == [0.0005, 0.001]
    assert all(r["status"] in ("ok", "stopped") for r in result.rows)
    assert all(isinstance(r["val/loss"], float) for r in result.rows) and result.best is not None
    # a trial that ran to the end has its finished point folder; one ASHA stopped early is listed as stopped, with
    # the step it stopped at and its (unfinished) folder
    finished = [r for r in result.rows if r["status"] == "ok"]
    assert finished and all((tmp_path / "lr" / "points" / r["point"] / "metrics.json").exists() for r in finished)
    assert all(r["stopped_at_step"] == r["step"] < 4 and r["point"] for r in result.rows if r["status"] == "stopped")


@pytest.mark.slow
def test_sampling_grows_its_actor_pool_when_nodes_join(tiny, tmp_path, monkeypatch):
    """The cluster has room for one sampling actor at the start and for two after the first batch (a node
    joined, as actor_count sees it): the second actor is started and takes the remaining batches."""
    import spread.sampling.run as run
    from spread.configs import to_object

    from helpers import FAST_SAMPLE, compose

    sizes = iter([1])
    real = run.actor_count
    monkeypatch.setattr(run, "actor_count", lambda cfg, batches: next(sizes, None) or real(cfg, batches))
    cfg = to_object(compose("sample", *FAST_SAMPLE, f"ckpt={tiny['ckpt']}", f"data.root={tiny['data']}",
                            f"out_dir={tmp_path / 's'}", "workers=2", "batch_size=1", "ray.num_cpus=2",
                            "samples_per_graph=2"))
    result = run.run_sampling(cfg)
    assert result.manifest["runner"]["workers"] == 2 and len(result.written) == 6
