"""benchmarks/learning_curve.py: pooling as spread-evaluate does (ratios of sums), bootstrap intervals over
scenes, the checkpoint ↔ clock bookkeeping, checkpoint selection, and the report's table and plot."""

import json

import numpy as np
import pytest

from helpers import load_script


@pytest.fixture(scope="module")
def lc():
    return load_script("learning_curve")


def record(matches, pairs, colliding, objects, asd, unchanged=None, stab_pairs=None):
    r = {"scene_id": "s", "objects": objects, "grecall_matches": matches, "grecall_pairs": pairs,
         "colliding": colliding, "asd_abs": list(asd)}
    if unchanged is not None:
        r.update(stability_unchanged=unchanged, stability_pairs=stab_pairs)
    return r


def test_pooled_metrics_are_ratios_of_sums_over_scenes_not_means_of_ratios(lc):
    records = [record(9, 10, 1, 10, [0.01, 0.03]), record(0, 2, 2, 2, [0.5])]
    out = lc.pooled(records)
    assert out["grecall"] == pytest.approx(9 / 12)  # a mean of ratios would give 0.45
    assert out["col_mesh"] == pytest.approx(3 / 12)
    assert out["asd"] == pytest.approx(0.54 / 3)
    assert "stability" not in out  # no scene was simulated


def test_bootstrap_interval_brackets_the_pooled_value_and_collapses_for_identical_scenes(lc):
    rng = np.random.default_rng(1)
    records = [record(int(m), 10, int(c), 8, rng.uniform(0, 0.1, 3), int(u), 20)
               for m, c, u in zip(rng.integers(0, 11, 60), rng.integers(0, 9, 60), rng.integers(10, 21, 60))]
    intervals = lc.bootstrap(records, resamples=500, seed=0)
    point = lc.pooled(records)
    for key in ("grecall", "col_mesh", "asd", "stability"):
        value, low, high = intervals[key]
        assert value == pytest.approx(point[key])
        assert low < value < high
    same = lc.bootstrap([record(7, 10, 2, 8, [0.02], 18, 20)] * 30, resamples=200)
    for value, low, high in same.values():
        assert low == pytest.approx(value) and high == pytest.approx(value)
    assert lc.bootstrap(records, resamples=500, seed=0) == intervals  # seeded


def test_paired_difference_matches_graphs_by_id_and_is_narrower_than_two_unpaired_intervals(lc):
    rng = np.random.default_rng(2)
    base = []
    for i, (m, c) in enumerate(zip(rng.integers(2, 9, 80), rng.integers(0, 6, 80))):
        r = record(int(m), 10, int(c), 8, rng.uniform(0, 0.1, 3))
        r["scene_id"] = f"g{i}"
        base.append(r)
    better = [dict(r, grecall_matches=r["grecall_matches"] + 1) for r in base][::-1]  # +1 match per graph, reordered
    d = lc.paired_difference(better, base, resamples=500)
    assert d["grecall"][0] == pytest.approx(0.1)  # 80 more matches of 800 pairs
    assert d["grecall"][1] == pytest.approx(0.1) and d["grecall"][2] == pytest.approx(0.1)  # every graph +1: no spread
    assert d["col_mesh"] == pytest.approx((0.0, 0.0, 0.0)) and d["asd"] == pytest.approx((0.0, 0.0, 0.0))
    a, b = lc.bootstrap(better, resamples=500), lc.bootstrap(base, resamples=500)
    assert a["grecall"][1] - b["grecall"][2] < 0.1 - 1e-6  # unpaired, the two intervals overlap or nearly so
    other = [dict(r, scene_id="x" + r["scene_id"]) for r in base]
    assert lc.paired_difference(other, base) == {}  # no graph in common: nothing to compare


def make_run(tmp_path, steps, clock_lines, last=True):
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    for s in steps:
        (run / "checkpoints" / f"step{s:07d}.ckpt").write_bytes(b"")
    if last:
        (run / "checkpoints" / "last.ckpt").write_bytes(b"")
    (run / "checkpoints" / "step0000100-v1.ckpt").write_bytes(b"")  # not a step file name: ignored
    (run / "clock.jsonl").write_text("".join(json.dumps(c) + "\n" for c in clock_lines))
    return run


def test_last_checkpoint_takes_the_clocks_newest_step_and_step_files_keep_theirs(lc, tmp_path):
    clock = [{"step": 1000, "scenes": 16000, "seconds": 250.0}, {"step": 1000, "scenes": 16000, "seconds": 251.0},
             {"step": 2000, "scenes": 32000, "seconds": 500.0}, {"step": 2345, "scenes": 37520, "seconds": 590.0}]
    run = make_run(tmp_path, [1000, 2000], clock)
    found = lc.checkpoints(run)
    assert list(found) == [1000, 2000, 2345]
    assert found[1000].name == "step0001000.ckpt" and found[2345].name == "last.ckpt"
    assert lc.clock(run)[1000]["seconds"] == 251.0  # the newest record of a step
    # the final save at a step that has its own file does not replace it
    run2 = make_run(tmp_path / "b", [1000, 2000], clock[:3])
    assert {s: p.name for s, p in lc.checkpoints(run2).items()} == {1000: "step0001000.ckpt",
                                                                      2000: "step0002000.ckpt"}


def test_pick_names_checkpoints_by_step_last_or_all_and_rejects_unknown_steps(lc):
    steps = [1000, 2000, 3000]
    assert lc.pick(["last"], steps) == {3000}
    assert lc.pick(["1000", "last"], steps) == {1000, 3000}
    assert lc.pick(["all"], steps) == set(steps)
    assert lc.pick([], steps) == set()
    with pytest.raises(ValueError, match="1500"):
        lc.pick(["1500"], steps)
    with pytest.raises(ValueError, match="final"):
        lc.pick(["final"], steps)


def test_report_places_each_curve_file_on_steps_scenes_and_minutes_and_draws_the_plot(lc, tmp_path, capsys):
    run = make_run(tmp_path, [1000, 2000], [{"step": 1000, "scenes": 16000, "seconds": 240.0},
                                             {"step": 2000, "scenes": 32000, "seconds": 480.0}], last=False)
    (run / "curve").mkdir()
    rows = {"0001000_unguided": [record(5, 10, 4, 8, [0.3]), record(6, 10, 3, 8, [0.2])],
            "0002000_unguided": [record(8, 10, 2, 8, [0.1]), record(9, 10, 1, 8, [0.05])],
            "0002000_guided": [record(9, 10, 0, 8, [0.01], 19, 20), record(9, 10, 1, 8, [0.02], 20, 20)]}
    for name, records in rows.items():
        (run / "curve" / f"{name}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
        assert lc.has_stability(run / "curve" / f"{name}.jsonl") == (name.endswith("guided")
                                                                       and not name.endswith("unguided"))
    loaded = {(r["step"], r["mode"]): r for r in lc.load_run(run)}
    assert loaded[(2000, "guided")]["scenes_seen"] == 32000 and loaded[(1000, "unguided")]["seconds"] == 240.0
    assert loaded[(2000, "unguided")]["metrics"]["grecall"][0] == pytest.approx(0.85)
    png = tmp_path / "curve.png"
    lc.main(["report", f"tiny={run}", "--png", str(png), "--targets"])
    table = capsys.readouterr().out
    assert "| tiny | unguided | 2000 | 32000 | 8.0 | 2 | 0.850 [" in table
    assert "| tiny | guided | 2000 |" in table and "Stability" in table
    assert png.stat().st_size > 10_000


def test_report_pairs_the_guided_samples_when_asked_and_the_unguided_ones_by_default(lc, tmp_path, capsys):
    """Two runs with the same unguided samples and different refinements: --paired-mode guided gives the guided
    difference (Col_mesh 0.3 -> 0.1 on the same two graphs), the default the unguided one (nothing)."""
    runs = []
    for name, guided_colliding in (("ref", (2, 4)), ("new", (1, 1))):
        run = make_run(tmp_path / name, [2000], [{"step": 2000, "scenes": 32000, "seconds": 480.0}], last=False)
        (run / "curve").mkdir()
        rows = {"0002000_unguided": [dict(record(8, 10, 3, 10, [0.1]), scene_id=g) for g in ("a", "b")],
                "0002000_guided": [dict(record(8, 10, c, 10, [0.05]), scene_id=g)
                                   for g, c in zip(("a", "b"), guided_colliding)]}
        for mode, records in rows.items():
            (run / "curve" / f"{mode}.jsonl").write_text("".join(json.dumps(r) + "\n" for r in records))
        runs.append(f"{name}={run}")
    lc.main(["report", *runs, "--paired-against", "ref", "--paired-mode", "guided"])
    out = capsys.readouterr().out
    assert "against ref (step 2000, guided)" in out and "| new | 2000 | 32000 | 8.0 | 0.000 [" in out
    assert "| -0.200 [-0.300, -0.100] |" in out  # ΔCol_mesh per graph: −0.1 and −0.3
    lc.main(["report", *runs, "--paired-against", "ref"])
    out = capsys.readouterr().out
    assert "against ref (step 2000, unguided)" in out and "| 0.000 [0.000, 0.000] | 0.0 [" in out


def test_report_logs_each_curve_as_an_offline_wandb_run(lc, tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_MODE", "offline")
    run = make_run(tmp_path, [1000], [{"step": 1000, "scenes": 16000, "seconds": 240.0}], last=False)
    (run / "curve").mkdir()
    (run / "curve" / "0001000_unguided.jsonl").write_text(json.dumps(record(5, 10, 4, 8, [0.3])) + "\n")
    folders = lc.log_wandb({"tiny": lc.load_run(run)}, tmp_path / "wb")
    assert len(folders) == 1 and folders[0]
    logged = list((tmp_path / "wb" / "wandb").glob("offline-run-*/run-*.wandb"))
    assert len(logged) == 1 and logged[0].stat().st_size > 0
