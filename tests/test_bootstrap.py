"""Confidence intervals: the bootstrap over scenes of the pooled metrics, and how tables print them."""

import json

import numpy as np
import pytest

from spread.evaluation.bootstrap import bootstrap_intervals, interval_note, resample_indices
from spread.reporting.intervals import grouped_intervals

#: The known answer of what each pooled value is (DESIGN §6): value → (state block, numerator, denominator).
#: The bootstrap asks each registered metric for these terms; this test states them independently.
RATIOS = {
    "col_mesh": ("col_mesh", "colliding_objects", "objects"),
    "grecall": ("grecall", "matches", "pairs"),
    "asd": ("asd", "abs_distance_sum", "pairs"),
    "stability": ("stability", "unchanged_pairs", "pairs"),
    "still_fraction": ("stability", "still_objects", "objects"),
}


def record(scene_id, colliding, objects, matches, pairs, asd_sum=0.0, support=0, unchanged=None, still=None,
           error=None):
    """A per_scene.jsonl line as the evaluation writes it (only what the bootstrap reads)."""
    if error:
        return {"scene_id": scene_id, "error": error}
    unchanged = matches if unchanged is None else unchanged
    still = objects if still is None else still
    return {"scene_id": scene_id, "error": None, "num_objects": objects, "state": {
        "col_mesh": {"colliding_objects": colliding, "objects": objects},
        "grecall": {"matches": matches, "pairs": pairs},
        "asd": {"abs_distance_sum": asd_sum, "pairs": support},
        "stability": {"unchanged_pairs": unchanged, "pairs": pairs, "objects": objects, "still_objects": still,
                      "displacement_ok": still, "rotation_ok": still}}}


def test_two_scenes_give_the_interval_between_their_own_ratios():
    """Two scenes A, B: a resample is AA, AB, BA or BB (1/4, 1/2, 1/4), so the 2.5 % and 97.5 % quantiles of
    10,000 resamples are A's and B's own ratios (each has probability 1/4 > 2.5 %) — known by hand."""
    a = record("a", colliding=1, objects=2, matches=2, pairs=2)     # Col 0.5, GRecall 1.0
    b = record("b", colliding=0, objects=8, matches=28, pairs=56)   # Col 0.0, GRecall 0.5
    out = bootstrap_intervals([a, b], resamples=10_000, seed=1)
    assert (out["col_mesh_lo"], out["col_mesh_hi"]) == (0.0, 0.5)
    assert (out["grecall_lo"], out["grecall_hi"]) == (0.5, 1.0)
    assert out["bootstrap"] == {"method": "percentile", "unit": "scene", "resamples": 10_000, "level": 0.95,
                                "seed": 1, "n_scenes": 2, "measured": {m: 2 for m in RATIOS} | {"asd": 0}}


def test_interval_is_the_percentile_interval_of_pooled_ratios_of_resampled_scenes():
    """Against a plain loop over the same resamples: pooled Σ num / Σ den per resample (not a mean of ratios)."""
    rng = np.random.default_rng(5)
    records = []
    for k in range(23):
        n = int(rng.integers(2, 30))
        pairs = n * (n - 1)
        support = int(rng.integers(0, 4))
        records.append(record(f"s{k}", colliding=int(rng.integers(0, n + 1)), objects=n,
                              matches=int(rng.integers(0, pairs + 1)), pairs=pairs,
                              asd_sum=float(rng.uniform(0, 0.05) * support), support=support,
                              unchanged=int(rng.integers(0, pairs + 1)), still=int(rng.integers(0, n + 1))))
    records.insert(7, record("broken", 0, 0, 0, 0, error="ValueError: unknown asset"))  # left out
    out = bootstrap_intervals(records, resamples=400, level=0.9, seed=3)
    good = [r for r in records if not r.get("error")]
    index = resample_indices(len(good), 400, 3)
    for metric, (block, num, den) in RATIOS.items():
        values = []
        for row in index:
            n_sum = sum(good[i]["state"][block][num] for i in row)
            d_sum = sum(good[i]["state"][block][den] for i in row)
            if d_sum > 0:
                values.append(n_sum / d_sum)
        lo, hi = np.percentile(values, [5, 95])
        assert out[f"{metric}_lo"] == pytest.approx(lo, abs=1e-12) and out[f"{metric}_hi"] == pytest.approx(hi, abs=1e-12)
    assert out["bootstrap"]["n_scenes"] == 23


def test_pooled_not_averaged_and_reproducible_by_seed():
    # equal per-scene ratios in every scene: every resample gives that ratio, so lo = hi = it
    same = [record(f"s{k}", colliding=k, objects=4 * k, matches=k, pairs=2 * k) for k in range(1, 6)]
    out = bootstrap_intervals(same, resamples=200, seed=0)
    assert out["col_mesh_lo"] == pytest.approx(0.25) and out["col_mesh_hi"] == pytest.approx(0.25)
    assert out["grecall_lo"] == pytest.approx(0.5) and out["grecall_hi"] == pytest.approx(0.5)
    # pooled, not averaged: 3 small rooms (1 of 2 objects colliding) and 3 big ones (0 of 8). The number k of
    # small rooms in a resample is Binomial(6, 1/2) and P(k <= 2) = 22/64 < 0.4, P(k <= 3) = 42/64 > 0.6, so
    # the central 20 % interval is k = 3's pooled ratio 3/30 = 0.1 (a mean of ratios would give 0.25)
    lopsided = [record("small", 1, 2, 1, 2)] * 3 + [record("big", 0, 8, 1, 2)] * 3
    out = bootstrap_intervals(lopsided, resamples=20_000, level=0.2, seed=0)
    assert out["col_mesh_lo"] == pytest.approx(0.1) and out["col_mesh_hi"] == pytest.approx(0.1)
    varied = [record(f"s{k}", colliding=k % 3, objects=5, matches=k, pairs=20, asd_sum=0.01 * np.sqrt(k + 1),
                     support=1 + k % 2) for k in range(15)]
    assert bootstrap_intervals(varied, seed=4) == bootstrap_intervals(varied, seed=4)
    assert bootstrap_intervals(varied, seed=4)["asd_lo"] != bootstrap_intervals(varied, seed=5)["asd_lo"]


def test_metrics_nobody_measured_have_no_interval_and_bad_input_is_named():
    rows = [record("a", 0, 3, 6, 6), record("b", 1, 3, 3, 6)]  # no support pairs anywhere: ASD undefined
    out = bootstrap_intervals(rows * 3 + [record("c", 0, 2, 2, 2, asd_sum=0.01, support=1)], resamples=50)
    assert out["asd_lo"] == out["asd_hi"] == 0.01 and out["bootstrap"]["measured"]["asd"] == 1  # one room: say so
    assert interval_note(out["bootstrap"]).endswith(
        "seed 0); FID and KID have none. Fewer than 5 scenes measured asd (1): too few for a trustworthy interval.")
    out = bootstrap_intervals(rows, resamples=50)
    assert out["asd_lo"] is None and out["asd_hi"] is None and out["grecall_lo"] is not None
    empty = bootstrap_intervals([], resamples=50)
    assert empty["grecall_lo"] is None and empty["bootstrap"]["n_scenes"] == 0
    # a state the metric keeps is missing: the record is a failed scene (docs/robustness.md round 15), left out
    missing = bootstrap_intervals([{"scene_id": "x", "error": None, "state": {"col_mesh": {"objects": 1}}}])
    assert missing["bootstrap"]["n_scenes"] == 0 and missing["col_mesh_lo"] is None
    lacking = bootstrap_intervals([record("x", 0, 3, 6, 6), {"scene_id": "y", "error": None, "state": {
        "col_mesh": {"colliding_objects": 0, "objects": 1}}}])  # one scene lacks a metric the rest have: left out
    assert lacking["bootstrap"]["n_scenes"] == 1
    with pytest.raises(ValueError, match="level"):
        bootstrap_intervals(rows, level=95)
    assert "95 % percentile bootstrap interval over scenes (1,000 resamples, seed 0)" in \
        interval_note(bootstrap_intervals(rows)["bootstrap"])


def test_finite_states_whose_sums_overflow_give_no_interval_never_a_nan():
    """A line whose ASD sum is 1.7e308 (finite, so usable): the resampled sums overflow to inf and ``np.quantile``
    made the bounds NaN, written into metrics.json (which spread-report then refuses): none now, other metrics kept."""
    import math

    rows = [record(k, 0, 3, 6, 6, asd_sum=1.7e308, support=1) for k in "abc"]
    out = bootstrap_intervals(rows, resamples=50)
    assert out["asd_lo"] is None and out["asd_hi"] is None
    assert out["grecall_lo"] == out["grecall_hi"] == 1.0
    assert all(v is None or math.isfinite(v) for k, v in out.items() if k != "bootstrap")
    json.dumps(out, allow_nan=False)


def random_rooms(n, seed):
    """n rooms of 2-30 objects with random collisions, relations, support gaps and physics outcomes."""
    rng = np.random.default_rng(seed)
    rooms = []
    for k in range(n):
        objects = int(rng.integers(2, 31))
        pairs = objects * (objects - 1)
        support = int(rng.integers(1, 5))
        rooms.append(record(f"r{seed}_{k}", colliding=int(rng.binomial(objects, 0.2)), objects=objects,
                            matches=int(rng.binomial(pairs, 0.8)), pairs=pairs,
                            asd_sum=float(rng.exponential(0.05) * support), support=support,
                            unchanged=int(rng.binomial(pairs, 0.9)), still=int(rng.binomial(objects, 0.7))))
    return rooms


@pytest.mark.parametrize("seed", range(5))
def test_interval_contains_the_reported_metric(seed):
    """lo <= the value metrics.json reports (the torchmetrics merge of the same records) <= hi, every metric."""
    from spread.evaluation.aggregate import summary_values
    from spread.evaluation.protocol import EvalProtocol

    rooms = random_rooms(12 + 7 * seed, seed)
    reported = summary_values(rooms, EvalProtocol())
    out = bootstrap_intervals(rooms, seed=seed)
    for metric in RATIOS:
        assert out[f"{metric}_lo"] <= reported[metric] <= out[f"{metric}_hi"], metric
        assert out[f"{metric}_lo"] < out[f"{metric}_hi"], metric  # varied rooms: a real interval


def test_interval_shrinks_with_more_scenes():
    """The same 10 rooms evaluated 16 times over keep the pooled value and narrow the interval ~4× (1/√n);
    40 and 160 independent rooms of the same kind are narrower than 10."""
    rooms = random_rooms(10, 0)
    few, many = bootstrap_intervals(rooms, seed=0), bootstrap_intervals(rooms * 16, seed=0)
    for metric in RATIOS:
        wide, narrow = (o[f"{metric}_hi"] - o[f"{metric}_lo"] for o in (few, many))
        assert 0.15 * wide < narrow < 0.4 * wide, metric
    widths = [{m: o[f"{m}_hi"] - o[f"{m}_lo"] for m in RATIOS}
              for o in (bootstrap_intervals(random_rooms(n, 1), seed=0) for n in (10, 40, 160))]
    for metric in RATIOS:
        assert widths[0][metric] > widths[1][metric] > widths[2][metric], metric


def test_constant_metric_has_a_zero_width_interval():
    """No room collides and every relation holds: Col_mesh is 0 and GRecall 1 in every resample."""
    rooms = [record(f"s{k}", colliding=0, objects=3 + k, matches=(3 + k) * (2 + k), pairs=(3 + k) * (2 + k),
                    asd_sum=0.01 * k, support=1) for k in range(9)]
    out = bootstrap_intervals(rooms, seed=7)
    assert out["col_mesh_lo"] == out["col_mesh_hi"] == 0.0
    assert out["grecall_lo"] == out["grecall_hi"] == 1.0
    assert out["asd_lo"] < out["asd_hi"]  # the gaps do vary


def test_same_seed_same_interval_other_seed_other_resamples():
    rooms = random_rooms(20, 3)
    first, again = bootstrap_intervals(rooms, seed=11), bootstrap_intervals(list(rooms), seed=11)
    assert first == again and first["bootstrap"]["seed"] == 11
    other = bootstrap_intervals(rooms, seed=12)
    assert any(first[f"{m}_lo"] != other[f"{m}_lo"] for m in RATIOS)


# ---- tables ----------------------------------------------------------------------------------------

def test_tables_print_value_plus_minus_half_width_and_csv_keeps_the_bounds(tmp_path):
    from spread.reporting.tables import Column, metric_columns, read_csv, write_tables

    rows = [{"method": "A", "grecall": 0.8, "grecall_lo": 0.75, "grecall_hi": 0.83, "asd": 0.0123,
             "asd_lo": 0.01, "asd_hi": 0.0152, "fid": 12.0},
            {"method": "B", "grecall": 0.9, "grecall_lo": None, "grecall_hi": None, "asd": None}]
    columns = [Column("method", "Method"), *[c for c in metric_columns() if c.key in ("grecall", "asd", "fid")]]
    paths = write_tables(rows, columns, tmp_path / "t", caption="cap", note="± is what it is.")
    md = paths["md"].read_text()
    assert "| GRecall ↑ | ASD (mm) ↓ | FID ↓ |" in md  # ASD shown in its registered unit, mm
    assert "| A | 0.800 ± 0.040 | 12.3 ± 2.6 | 12.00 |" in md
    assert "| B | **0.900** | – | – |" in md and md.rstrip().endswith("± is what it is.")
    tex = paths["tex"].read_text()
    assert r"0.800\,{\scriptsize$\pm$0.040}" in tex and "± is what it is." not in tex and r"$\pm$ is what" in tex
    back = read_csv(paths["csv"])
    assert back[0]["asd_mm"] == pytest.approx(12.3) and "asd" not in back[0]  # in mm, as its header says
    assert (back[0]["asd_mm_lo"], back[0]["asd_mm_hi"]) == pytest.approx((10.0, 15.2))
    assert back[0]["grecall_lo"] == 0.75 and back[0]["grecall_hi"] == 0.83 and back[1]["grecall_lo"] is None
    assert list(back[0])[:4] == ["method", "grecall", "grecall_lo", "grecall_hi"]


def test_evaluation_metrics_json_carries_the_intervals_of_its_records(tmp_path):
    """What run_evaluation adds to metrics.json is bootstrap_intervals of the per-scene lines it wrote."""
    from spread.reporting.intervals import row_intervals

    rows = [record(f"s{k}", colliding=k % 2, objects=4, matches=k, pairs=12) for k in range(6)]
    folder = tmp_path / "eval"
    folder.mkdir()
    (folder / "per_scene.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    metrics = {"grecall": 0.2, "col_mesh": 0.5}
    fields = row_intervals(metrics, folder)  # an older metrics.json: computed from per_scene.jsonl
    assert fields == bootstrap_intervals(rows, seed=0)
    stored = {**metrics, **bootstrap_intervals(rows, resamples=10, seed=2)}
    assert row_intervals(stored, folder)["bootstrap"]["resamples"] == 10  # metrics.json's own win
    assert row_intervals(metrics, tmp_path / "nowhere") == {}


def test_any_table_with_bounds_prints_them_and_its_csv_names_the_seed(tmp_path):
    """A table with its own columns and csv_keys (as compare's Table 1 passes) gets ± cells, the bounds after
    each value and the bootstrap's settings at the end of the CSV, without naming them."""
    from spread.reporting.intervals import ci_columns, grouped_intervals, table_note
    from spread.reporting.tables import Column, read_csv, write_tables

    rooms = random_rooms(16, 2)
    kind = {r["scene_id"]: ("bedroom" if k % 2 else "kitchen") for k, r in enumerate(rooms)}
    row = {"method": "SPREAD", "col_mesh": 0.2, **ci_columns(bootstrap_intervals(rooms, seed=9)),
           **grouped_intervals(rooms, kind.get, ["col_mesh"], seed=9)}
    columns = [Column("method", "Method"), Column("col_mesh", "Col_mesh", 3, "min"),
               Column("col_mesh/bedroom", "Col_mesh bedroom", 3, "min")]
    paths = write_tables([row], columns, tmp_path / "table1", csv_keys=["method", "col_mesh", "col_mesh/bedroom"],
                         note=table_note([row]))
    back = read_csv(paths["csv"])[0]
    assert list(back) == ["method", "col_mesh", "col_mesh_lo", "col_mesh_hi", "col_mesh/bedroom",
                          "col_mesh/bedroom_lo", "col_mesh/bedroom_hi", "ci_level", "ci_resamples", "ci_seed",
                          "ci_few"]
    assert back["ci_seed"] == 9 and back["ci_resamples"] == 1000 and back["ci_few"] is None  # 16 rooms measured all
    half = (row["col_mesh/bedroom_hi"] - row["col_mesh/bedroom_lo"]) / 2
    assert f"| {row['col_mesh/bedroom']:.3f} ± {half:.3f} |" in paths["md"].read_text()
    assert "seed 9" in paths["md"].read_text() and "Fewer than" not in paths["md"].read_text()
    # two rooms with support pairs among six: the row says ASD's interval is not to be trusted
    rows = [record(f"s{k}", 0, 4, 6, 12, asd_sum=0.01 * k, support=int(k < 2)) for k in range(6)]
    flagged = {"method": "B", **ci_columns(bootstrap_intervals(rows, seed=0))}
    assert flagged["ci_few"] == "asd (2)"
    assert table_note([row, flagged]).endswith(
        "Fewer than 5 scenes measured B: asd (2): too few for a trustworthy interval.")


def test_grouped_intervals_bootstrap_each_group_on_its_own_scenes():
    rooms = random_rooms(20, 4)
    group = {r["scene_id"]: ("a" if k < 6 else "b" if k < 18 else None) for k, r in enumerate(rooms)}
    out = grouped_intervals(rooms, group.get, ["col_mesh", "grecall"], seed=1)
    for name, members in (("a", rooms[:6]), ("b", rooms[6:18])):
        alone = bootstrap_intervals(members, seed=1)
        sums = [sum(r["state"]["col_mesh"][k] for r in members) for k in ("colliding_objects", "objects")]
        assert out[f"col_mesh/{name}"] == pytest.approx(sums[0] / sums[1])
        assert (out[f"grecall/{name}_lo"], out[f"grecall/{name}_hi"]) == (alone["grecall_lo"], alone["grecall_hi"])
        assert out[f"col_mesh/{name}_lo"] <= out[f"col_mesh/{name}"] <= out[f"col_mesh/{name}_hi"]
    with pytest.raises(ValueError, match="unknown metric 'fid'"):
        grouped_intervals(rooms, group.get, ["fid"])


def test_make_demo_table_prints_each_cell_with_its_interval():
    """make demo's ground truth | generated table: value ± half-width, ASD in mm, '–' for a missing metric."""
    from rich.console import Console

    from spread.cli.demo import comparison_table

    truth = {"grecall": 1.0, "grecall_lo": 1.0, "grecall_hi": 1.0, "col_mesh": 0.0, "asd": None,
             "stability": 0.99, "n_scenes": 8, "n_objects": 60}
    generated = {"grecall": 0.8, "grecall_lo": 0.75, "grecall_hi": 0.85, "col_mesh": 0.2, "col_mesh_lo": 0.1,
                 "col_mesh_hi": 0.3, "asd": 0.25, "asd_lo": 0.2, "asd_hi": 0.31, "stability": 0.9,
                 "n_scenes": 8, "n_objects": 61}
    console = Console(width=200, record=True)
    console.print(comparison_table(truth, generated, "t"))
    text = console.export_text()
    assert "1.000 ± 0.000" in text and "0.800 ± 0.050" in text and "0.200 ± 0.100" in text
    assert "250.0 ± 55.0" in text and "–" in text
