"""Results you can query (issue 31 item 6; spread.results): a sweep folder as a DataFrame with every differing
setting a column, intervals over seeds, the paired difference of two points, parameter importance, the Pareto
front, ASHA's stopped trials, and spread-report's analysis section — each against synthetic folders shaped as
the commands write them (a sweep with ``seeds=K``: one results.csv row per (point values, seed), its ``seed`` and
its ``point`` folder under points/)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from spread.results import importance, load, over_seeds, paired_difference, pareto, stopped_trials
from spread.results.frame import display


def write_point(folder: Path, collision: float, iterations: int, seed: int, values: dict, scenes=None) -> None:
    """A finished sampling point: point.json (its identity), metrics.json (values with intervals), and
    per_scene.jsonl (``scenes``: scene id → {metric: value})."""
    folder.mkdir(parents=True)
    identity = {"guidance": {"mode": "refine", "collision": collision, "gravity": 0.001, "iterations": iterations},
                "sampling": {"seed": seed, "batch_size": 2}, "samples_per_graph": 1}
    (folder / "point.json").write_text(json.dumps({"status": "finished", "fingerprint": identity, "short": "x"}))
    metrics = {"n_scenes": 3, "n_evaluated": 3, "n_failed": 0, "fid_status": "disabled",
               "bootstrap": {"level": 0.95, "resamples": 100, "seed": 0, "method": "percentile"}}
    for k, v in values.items():
        metrics |= {k: v, f"{k}_lo": v - 0.05, f"{k}_hi": v + 0.05}
    (folder / "metrics.json").write_text(json.dumps(metrics))
    if scenes is not None:
        (folder / "per_scene.jsonl").write_text("".join(json.dumps({"scene_id": s, **v}) + "\n" for s, v in scenes.items()))


def write_sweep(root: Path, points: list[tuple]) -> Path:
    """``points``: (collision, iterations, seed, {metric: value}); results.csv as the sweep writes it."""
    rows = []
    for i, (collision, iterations, seed, values) in enumerate(points):
        name = f"collision{collision}_{i:02d}"
        write_point(root / "points" / name, collision, iterations, seed, values)
        rows.append({"guidance.collision": collision, "seed": seed, "point": name, "status": "ok", "reused": False,
                     "best": False, **values})
    pd.DataFrame(rows).to_csv(root / "results.csv", index=False)
    return root


def test_a_sweep_folder_loads_with_every_differing_setting_a_column_in_stored_units(tmp_path):
    sweep = write_sweep(tmp_path / "S", [(0.0, 2, 0, {"grecall": 0.5, "col_mesh": 0.3, "asd": 0.002}),
                                         (0.01, 4, 0, {"grecall": 0.4, "col_mesh": 0.1, "asd": 0.001})])
    df = load(sweep)
    assert len(df) == 2 and {"guidance.collision", "guidance.iterations", "seed", "point"} <= set(df.columns)
    assert df["guidance.iterations"].tolist() == [2, 4] and df["guidance.collision"].tolist() == [0.0, 0.01]
    assert {"guidance.collision", "guidance.iterations", "guidance.mode", "seed"} <= set(df.attrs["settings"])
    assert df["grecall_lo"].tolist() == pytest.approx([0.45, 0.35]) and df["asd"].tolist() == [0.002, 0.001]
    assert (df["kind"] == "sweep").all() and df["identity"].nunique() == 2
    shown = display(df)  # ASD in millimetres, headed so, as the tables show it
    assert shown["asd_mm"].tolist() == pytest.approx([2.0, 1.0]) and shown["asd_mm_hi"][0] == pytest.approx(52.0)
    # a row whose point folder is gone keeps results.csv's values, back in stored units (the CSV has asd_mm)
    rows = pd.read_csv(sweep / "results.csv").rename(columns={"asd": "asd_mm"}).assign(asd_mm=[2.0, 1.0])
    rows.assign(point=["gone", rows["point"][1]]).to_csv(tmp_path / "T.csv", index=False)
    (tmp_path / "T").mkdir()
    (tmp_path / "T" / "points").symlink_to(sweep / "points")
    (tmp_path / "T.csv").rename(tmp_path / "T" / "results.csv")
    kept = load(tmp_path / "T")
    assert kept["asd"].tolist() == pytest.approx([0.002, 0.001]) and "asd_mm" not in kept.columns
    assert pd.isna(kept["guidance.iterations"][0]) and kept["guidance.iterations"][1] == 4
    # the same points read as plain run folders (no results.csv): the same settings and values
    plain = load(sweep / "points")
    assert sorted(plain["guidance.iterations"]) == [2, 4] and sorted(plain["grecall"]) == [0.4, 0.5]


def test_over_seeds_gives_the_mean_and_a_student_t_interval_per_point(tmp_path):
    values = {(0.0, 0): 0.5, (0.0, 1): 0.6, (0.0, 2): 0.7, (0.01, 0): 0.2, (0.01, 1): 0.4}
    sweep = write_sweep(tmp_path / "S", [(c, 2, s, {"grecall": v}) for (c, s), v in values.items()])
    out = over_seeds(load(sweep), "grecall").set_index("guidance.collision")
    assert out.loc[0.0, "n_seeds"] == 3 and out.loc[0.0, "seeds"] == [0, 1, 2]
    assert out.loc[0.0, "grecall"] == pytest.approx(0.6)
    half = 4.302652729911275 * 0.1 / math.sqrt(3)  # t(0.975, 2) · s / √n
    assert out.loc[0.0, "grecall_lo"] == pytest.approx(0.6 - half) and out.loc[0.0, "grecall_hi"] == pytest.approx(0.6 + half)
    half = 12.706204736174698 * math.sqrt(0.02) / math.sqrt(2)  # t(0.975, 1)
    assert out.loc[0.01, "grecall"] == pytest.approx(0.3) and out.loc[0.01, "grecall_hi"] == pytest.approx(0.3 + half)
    one = over_seeds(load(write_sweep(tmp_path / "one", [(0.0, 2, 0, {"grecall": 0.5})])), "grecall")
    assert one["n_seeds"].tolist() == [1] and math.isnan(one["grecall_lo"][0])



def test_a_mean_over_seeds_shows_its_sd_in_the_unit_of_its_mean_and_bounds(tmp_path):
    """ASD over seeds: mean, bounds and sd all in mm under ``asd_mm*`` (the sd stayed in metres as ``asd_sd``)."""
    sweep = write_sweep(tmp_path / "S", [(0.0, 2, s, {"asd": v}) for s, v in enumerate((0.002, 0.004))])
    shown = display(over_seeds(load(sweep), "asd"))
    assert shown["asd_mm"][0] == pytest.approx(3.0) and shown["asd_mm_sd"][0] == pytest.approx(1000 * math.sqrt(2e-6))
    assert shown["asd_mm_lo"][0] < 3.0 < shown["asd_mm_hi"][0] and "asd_sd" not in shown.columns


def test_over_seeds_counts_a_run_drawn_twice_once_and_reads_an_evaluation_seed_that_follows_the_seed_as_the_seed():
    rows = [{"guidance.collision": 0.0075, "seed": seed, "protocol.seed": seed, "point": f"c0.0075_seed{seed}_ab",
             "grecall": value} for seed, value in ((0, 0.2), (0, 0.2), (0, 0.2), (1, 0.4), (1, 0.4), (1, 0.4))]
    df = pd.DataFrame(rows)
    df.attrs = {"settings": ["guidance.collision", "seed", "protocol.seed"], "metrics": ["grecall"]}
    out = over_seeds(df, "grecall")
    assert len(out) == 1 and out["n_seeds"].tolist() == [2] and out["seeds"].tolist() == [[0, 1]]
    half = 12.706204736174698 * math.sqrt(0.02) / math.sqrt(2)  # two runs, t(0.975, 1): not six
    assert out["grecall_hi"][0] == pytest.approx(0.3 + half)
    df.loc[df["seed"] == 1, "protocol.seed"] = 7  # an evaluation seed of its own is a setting
    assert len(over_seeds(df, "grecall")) == 2
    # rows of no point folder (failed trials) are not one run drawn twice: each counts
    failed = pd.DataFrame([{"guidance.collision": c, "seed": 0, "point": None, "grecall": g}
                           for c, g in ((0.5, 0.1), (0.7, 0.2))])
    failed.attrs = {"settings": ["guidance.collision", "seed"], "metrics": ["grecall"]}
    assert sorted(over_seeds(failed, "grecall")["grecall"].tolist()) == [0.1, 0.2]


def test_a_run_that_lacks_a_setting_the_others_have_is_a_point_of_its_own_never_another_seed():
    """A ground-truth evaluation (no checkpoint, sampler or seed; its evaluation seed 0) beside two sampled seeds of
    one checkpoint: it was pooled with seed 0 as one point of two "seeds" (GRecall 0.58 between 1.0 and 0.17)."""
    from spread.results.frame import frame, swept_settings

    def record(run, settings, grecall):
        return {"run": run, "settings": settings, "grecall": grecall}

    sampled = [record(f"s{k}", {"ckpt": "4a35", "sampler": "ddim-4", "seed": k, "protocol.seed": k}, g)
               for k, g in ((0, 0.2), (1, 0.4))]
    df = frame([*sampled, record("gt", {"protocol.seed": 0}, 1.0)])
    out = over_seeds(df, "grecall").sort_values("grecall")
    assert out["n_seeds"].tolist() == [2, 1] and out["grecall"].tolist() == pytest.approx([0.3, 1.0])
    assert out["seeds"].tolist() == [[0, 1], []]
    assert swept_settings(df) == ["ckpt", "sampler"]  # the evaluation seed still follows the seed where there is one


def test_paired_difference_matches_scenes_and_gives_a_seeded_bootstrap_interval(tmp_path):
    a_vals = {f"g{i}_k0": 0.5 + 0.1 * (i % 3) for i in range(8)}
    b_vals = {f"g{i}_k0": 0.4 + 0.05 * (i % 2) for i in range(2, 10)}  # g2..g9: shares g2..g7 with A
    write_point(tmp_path / "A", 0.0, 2, 0, {"grecall": 0.6}, {s: {"grecall": v} for s, v in a_vals.items()})
    write_point(tmp_path / "B", 0.01, 2, 0, {"grecall": 0.4}, {s: {"grecall": v} for s, v in b_vals.items()})
    shared = sorted(set(a_vals) & set(b_vals))
    d = np.array([a_vals[s] - b_vals[s] for s in shared])
    out = paired_difference(tmp_path / "A", tmp_path / "B", "grecall", resamples=500, seed=3)
    assert out["n_pairs"] == 6 and out["diff"] == pytest.approx(d.mean())
    assert out["lo"] <= out["diff"] <= out["hi"] and out["lo"] > 0  # A is better on every shared scene
    index = np.random.default_rng(3).integers(0, 6, size=(500, 6))
    expected = np.quantile(d[index].mean(axis=1), [0.025, 0.975])
    assert (out["lo"], out["hi"]) == pytest.approx(tuple(expected))
    assert paired_difference(tmp_path / "A", tmp_path / "B", "grecall", resamples=500, seed=3) == out
    assert paired_difference(tmp_path / "A", tmp_path / "B", "grecall", resamples=500, seed=4)["lo"] != out["lo"]
    write_point(tmp_path / "C", 0.0, 2, 0, {"grecall": 0.6}, {"other_k0": {"grecall": 0.1}})
    with pytest.raises(ValueError, match="share no scene"):
        paired_difference(tmp_path / "A", tmp_path / "C", "grecall")


def test_paired_difference_over_seeds_pairs_each_seed_with_its_own(tmp_path):
    """A point with two seeds against another with the same two: scene ids repeat across seeds, each pair is
    (seed, scene)."""
    for name, base in (("A", 0.5), ("B", 0.3)):
        for seed in (0, 1):
            write_point(tmp_path / f"{name}{seed}", 0.0 if name == "A" else 0.01, 2, seed, {"grecall": base},
                        {f"g{i}": {"grecall": base + 0.1 * seed + 0.01 * i} for i in range(3)})
    out = paired_difference([tmp_path / "A0", tmp_path / "A1"], [tmp_path / "B0", tmp_path / "B1"], "grecall",
                            resamples=200)
    assert out["n_pairs"] == 6 and out["diff"] == pytest.approx(0.2) and out["lo"] == pytest.approx(0.2)


def test_importance_ranks_the_setting_that_explains_the_variance():
    df = pd.DataFrame({"a": [0, 0, 1, 1], "b": [0, 1, 0, 1], "seed": [0, 1, 2, 3], "grecall": [1.0, 2.0, 5.0, 6.0]})
    df.attrs["settings"] = ["a", "b", "seed"]
    out = importance(df, "grecall")
    # SS total = 17; between a's levels (means 1.5, 5.5): 16; between b's (3, 4): 1; seed is not ranked
    assert out["setting"].tolist() == ["a", "b"]
    assert out["eta_squared"].tolist() == pytest.approx([16 / 17, 1 / 17]) and out["levels"].tolist() == [2, 2]



def test_an_evaluation_seed_that_follows_the_seed_is_not_ranked_or_shown_as_a_swept_setting():
    """A ``seeds=K`` sweep sets ``protocol.seed`` to each run's seed: the seed, not a setting (the analysis ranked
    it first, η² 0.98, ahead of the swept weight); one that does not follow the seed is a setting."""
    from spread.results.frame import swept_settings

    df = pd.DataFrame({"a": [0, 0, 1, 1], "seed": [0, 1, 0, 1], "protocol.seed": [0, 1, 0, 1],
                       "grecall": [1.0, 5.0, 1.2, 5.2]})
    df.attrs["settings"] = ["a", "seed", "protocol.seed"]
    assert importance(df, "grecall")["setting"].tolist() == ["a"] and swept_settings(df) == ["a"]
    df["protocol.seed"] = [3, 3, 4, 4]  # set on its own: a swept setting
    assert importance(df, "grecall")["setting"].tolist() == ["a", "protocol.seed"]
    assert swept_settings(df) == ["a", "protocol.seed"]


def test_pareto_keeps_only_rows_no_other_row_beats_in_both():
    df = pd.DataFrame({"run": list("abcde"), "col_mesh": [0.1, 0.2, 0.3, 0.2, 0.05],
                       "grecall": [0.5, 0.7, 0.9, 0.6, 0.4]})
    assert pareto(df)["run"].tolist() == ["e", "a", "b", "c"]  # d: b is as clean and recalls more
    assert pareto(df, minimize_x=False, maximize_y=False)["run"].tolist() == ["c", "d", "a", "e"]
    assert pareto(df.assign(col_mesh=[0.1, 0.1, 0.1, 0.1, 0.1]))["run"].tolist() == ["c"]


def write_trial(tune: Path, name: str, params: dict, results: list[dict], error: bool = False) -> None:
    folder = tune / "sweep" / name
    folder.mkdir(parents=True)
    (folder / "params.json").write_text(json.dumps(params))
    (folder / "result.json").write_text("".join(json.dumps({**r, "trial_id": name[-5:], "training_iteration": i + 1})
                                                + "\n" for i, r in enumerate(results)))
    if error:
        (folder / "error.txt").write_text("boom")


def test_stopped_trials_are_the_ones_asha_stopped_with_their_step(tmp_path):
    """As a ``command=train scheduler=asha`` sweep records them: every validation reported with its step; a trial
    that finished reports its point last; a stopped one does not; a failed one has error.txt."""
    tune = tmp_path / "S" / "tune"
    write_trial(tune, "train_trial_0_lr=0.001", {"model.lr": "0.001"},
                [{"val/loss": 1.0, "step": 2}, {"val/loss": 0.8, "step": 4}, {"val/loss": 0.8, "point": "lr0.001_ab"}])
    write_trial(tune, "train_trial_1_lr=0.1", {"model.lr": "0.1"}, [{"val/loss": 3.0, "step": 2}])
    write_trial(tune, "train_trial_2_lr=1", {"model.lr": "1"}, [{"val/loss": 9.0, "step": 2}], error=True)
    out = stopped_trials(tmp_path / "S")
    assert out["model.lr"].tolist() == ["0.1"] and out["step"].tolist() == [2] and out["val/loss"].tolist() == [3.0]
    # without Tune's records: results.csv's rows without a point
    other = tmp_path / "T"
    other.mkdir()
    pd.DataFrame([{"model.lr": 0.001, "point": "p", "status": "ok", "step": 4},
                  {"model.lr": 0.1, "point": None, "status": "ok", "step": 2}]).to_csv(other / "results.csv", index=False)
    assert stopped_trials(other)["model.lr"].tolist() == [0.1]


def test_spread_report_on_a_sweep_folder_adds_the_analysis_section(tmp_path):
    """spread-report on a seeds=2 sweep folder: importance, the Pareto front, the intervals over seeds, and with
    compare=[A,B] the paired difference; through the one table writer, ASD in mm."""
    from helpers import run_script

    points = [(c, it, s, {"grecall": g + 0.05 * s, "col_mesh": m, "asd": 0.001 * (1 + s)})
              for c, it, g, m in ((0.0, 2, 0.5, 0.3), (0.01, 2, 0.4, 0.1)) for s in (0, 1)]
    sweep = write_sweep(tmp_path / "S", points)
    for i, (c, _, s, values) in enumerate(points):
        folder = sweep / "points" / f"collision{c}_{i:02d}"
        (folder / "per_scene.jsonl").write_text("".join(json.dumps({"scene_id": f"g{j}", "grecall": values["grecall"]
                                                                    + 0.01 * j}) + "\n" for j in range(4)))
    out = tmp_path / "R"
    run_script("spread-report", f"runs={sweep}", f"out_dir={out}",
               "compare=[collision0.0_00,collision0.01_02]")
    md = (out / "analysis.md").read_text()
    assert "guidance.collision" in md and "η²" in md and "Pareto" in md and "over seeds" in md
    assert "paired difference" in md.lower() and "| GRecall | 0.515 | 0.415 | 0.100 ± 0.000 | 4 |" in md  # GRecall A − B on the same graphs and seed
    rows = pd.read_csv(out / "analysis_seeds.csv")
    assert rows["n_seeds"].tolist() == [2, 2] and "asd_mm" in rows.columns
    assert "analysis" in (out / "report.html").read_text().lower()


def test_spread_report_refuses_compare_of_a_point_with_itself_before_writing_anything(tmp_path):
    """A − B of a point against itself (or of patterns sharing a run) is 0 ± 0: no comparison; refused in one line."""
    from helpers import user_error

    sweep = write_sweep(tmp_path / "S", [(c, 2, s, {"grecall": 0.5, "col_mesh": 0.3}) for c in (0.0, 0.01)
                                         for s in (0, 1)])
    out = tmp_path / "R"
    line, _ = user_error("spread-report", f"runs={sweep}", f"out_dir={out}", "compare=[collision0.0_01,collision0.0_01]")
    assert line == ("spread-report: compare: 'collision0.0_01' and 'collision0.0_01' both name collision0.0_01; name "
                    "two points that share no run"), line
    line, _ = user_error("spread-report", f"runs={sweep}", f"out_dir={out}", "compare=[collision0.0_*,*_00]")
    assert "both name collision0.0_00;" in line and not out.exists(), line


def test_a_report_rewritten_in_its_folder_keeps_none_of_the_earlier_reports_outputs_and_a_run_folder_is_refused(
        tmp_path):
    """A second report into one ``out_dir`` left the first one's plots (of other runs) beside a ``report.json`` that
    listed none; a report into a run's folder rewrote its ``.hydra/config.yaml`` and wrote beside its results."""
    from helpers import user_error

    from spread.reporting.report import run_report

    sweep = write_sweep(tmp_path / "S", [(0.0, 2, 0, {"grecall": 0.5, "col_mesh": 0.3}),
                                         (0.01, 4, 0, {"grecall": 0.4, "col_mesh": 0.1})])
    out = tmp_path / "R"
    run_report([str(sweep)], out)
    plots = sorted((out / "plots").glob("*.png"))
    assert plots and (out / "report.csv").exists()
    kept = tmp_path / "mine.png"  # a hand-edited record naming a file outside the folder: never removed
    kept.write_bytes(b"x")
    record = json.loads((out / "report.json").read_text())
    record["plots"].append({"png": str(kept)})
    (out / "report.json").write_text(json.dumps(record))
    one = sweep / "points" / "collision0.0_00"
    run_report([str(one)], out)
    assert list((out / "plots").glob("*.png")) == [] and json.loads((out / "report.json").read_text())["plots"] == []
    assert kept.exists() and (out / "report.csv").exists() and "0.5" in (out / "report.csv").read_text()
    (one / "sampling.json").write_text("{}")  # a sampling run's folder, as spread-sample leaves one
    before = {p.name: p.read_bytes() for p in one.iterdir() if p.is_file()}
    line, _ = user_error("spread-report", f"runs={sweep}", f"out_dir={one}")
    assert line.startswith(f"spread-report: out_dir={one}: holds a sampling run"), line
    assert {p.name: p.read_bytes() for p in one.iterdir() if p.is_file()} == before


def test_an_mlflow_store_loads_as_runs_with_their_folders_settings_parent_and_reuse(tmp_path):
    """A store as a sweep logs it (spread.tracking.parent): a parent run (not a row), a trial run of each point
    (its out_dir param names the point folder: settings from the folder), a re-used point's child run."""
    import json as _json

    from spread.tracking import mlflow_store
    from spread.tracking.parent import parent_run

    sweep = write_sweep(tmp_path / "S", [(0.0, 2, 0, {"grecall": 0.5, "col_mesh": 0.3}),
                                         (0.01, 4, 0, {"grecall": 0.4, "col_mesh": 0.1})])
    logger = {"name": "mlflow", "tracking_uri": str(tmp_path / "mlflow.db")}
    folders = sorted((sweep / "points").iterdir(), key=lambda f: f.name[-2:])  # collision0.0 (2 iterations), 0.01 (4)
    with parent_run(logger, "sweep", "s", sweep, "s") as parent:
        for folder in folders:
            run = mlflow_store.open_run(logger, "sample", tmp_path / "elsewhere", {"out_dir": str(folder)}, "s")
            run.log_metrics(mlflow_store.scalar_metrics(_json.loads((folder / "metrics.json").read_text())))
            run.finish()
        row = {"point": folders[0].name, "reused": True, "grecall": 0.45}  # metrics.json's values win
        (reused,) = parent.log_reused([row], sweep / "points")
    df = load(tmp_path / "mlflow.db")
    assert len(df) == 3 and set(df["parent_run_id"]) == {parent.run.run_id}
    made = df[df["reused"]]
    assert made["run_id"].tolist() == [reused] and made["grecall"].tolist() == [0.5]
    first = df[~df["reused"]].sort_values("guidance.iterations")
    assert first["guidance.iterations"].tolist() == [2, 4] and first["grecall_lo"].tolist() == pytest.approx([0.45, 0.35])
    assert made["made_by_run_id"].tolist() == [first["run_id"].iloc[0]]
    # the re-used point's child has the point's settings (it had none: the swept value was a metric, not a setting),
    # and a mean over seeds counts the point's run once (the relaunch made it two "seeds")
    assert made["guidance.iterations"].tolist() == [2] and made["identity"].tolist() == [first["identity"].iloc[0]]
    means = over_seeds(df, "grecall").sort_values("guidance.iterations")
    assert means["n_seeds"].tolist() == [1, 1] and means["grecall"].tolist() == [0.5, 0.4]
