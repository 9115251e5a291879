"""Units in one place (issue 30): each metric's spec declares its values and display unit, and every writer —
the table writer's Markdown, CSV, LaTeX and HTML, the bar and metric-vs-setting plots, the sweep's results, the
report's files and page, the wandb tables, the evaluation's console table, the demo's table — shows ASD in mm
(``metrics.json`` keeps metres). Each writer's own output is read back here; the docs say mm too."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROWS = [{"variant": "base", "method": "Ours (base)", "grecall": 0.9, "col_mesh": 0.2, "asd": 0.0021,
         "asd_lo": 0.0019, "asd_hi": 0.0025, "stability": 0.95, "still_fraction": 0.8, "fid": None, "kid": None,
         "n_scenes": 4, "status": "ok"},
        {"variant": "geometry", "method": "+Geometry", "grecall": 0.91, "col_mesh": 0.1, "asd": 0.0042,
         "stability": 0.96, "still_fraction": 0.85, "fid": None, "kid": None, "n_scenes": 4, "status": "ok"}]
MM = [2.1, 4.2]  # the rows' ASD in mm


def test_a_metric_spec_declares_each_value_and_its_display_unit():
    from spread.metrics.registry import METRICS, display_values, value_spec

    assert [v.name for v in METRICS.get("stability").values] == ["stability", "still_fraction"]
    asd, still = value_spec("asd"), value_spec("still_fraction")
    assert (asd.unit, asd.scale, asd.label) == ("mm", 1000.0, "ASD (mm)") and asd.display(0.0021) == pytest.approx(2.1)
    assert still.label == "Still" and not still.shown and still.description
    assert "still_fraction" in [v.name for v in display_values()] and value_spec("fid").label == "FID"


def test_the_table_writer_shows_asd_in_mm_in_markdown_csv_latex_and_html(tmp_path):
    from spread.experiments.ablation import write_ablation_table
    from spread.reporting.tables import columns_of, html_table, read_csv

    paths = write_ablation_table(ROWS, tmp_path / "ablation")
    md, tex = paths["md"].read_text(), paths["tex"].read_text()
    assert "ASD (mm)" in md and "| **2.1 ± 0.3** |" in md and "| 4.2 |" in md  # lower is better: 2.1 is bold
    assert "ASD (mm)" in tex and "2.1" in tex and "0.0021" not in tex
    back = read_csv(paths["csv"])
    assert [r["asd_mm"] for r in back] == pytest.approx(MM) and "asd" not in back[0]
    assert (back[0]["asd_mm_lo"], back[0]["asd_mm_hi"]) == pytest.approx((1.9, 2.5))
    assert [r["still_fraction"] for r in back] == [0.8, 0.85]  # every registered value reaches the CSV
    html = html_table(ROWS, columns_of(ROWS))
    assert "<th>ASD (mm) ↓</th>" in html and "<td>2.1 ± 0.3</td>" in html


def test_the_table_across_training_seeds_shows_asd_and_its_sd_in_mm(tmp_path):
    from spread.experiments.ablation_seeds import write_seed_table
    from spread.reporting.tables import read_csv

    rows = [{**r, "seeds": 2, "asd_sd": 0.0005} for r in ROWS]
    paths = write_seed_table(rows, tmp_path / "ablation", [0, 1])
    back = read_csv(paths["csv"])
    assert [r["asd_mm"] for r in back] == pytest.approx(MM) and back[0]["asd_mm_sd"] == pytest.approx(0.5)
    assert "2.1 ± 0.5 (± 0.3)" in paths["md"].read_text()


def test_plots_draw_asd_in_mm(tmp_path):
    from spread.reporting.plots import ablation_bars, metric_vs_weight
    from spread.reporting.tables import value_column

    asd = value_column("asd")
    drawn = ablation_bars(ROWS, [asd], tmp_path / "bars.png", label_key="method")
    assert drawn["asd"] == pytest.approx(MM) and drawn["asd:error"][0] == pytest.approx([0.2, 0.4])
    runs = [{**r, "guidance.collision": w} for r, w in zip(ROWS, (0.0, 0.0075))]
    points = metric_vs_weight(runs, asd, "guidance.collision", tmp_path / "vs.png")
    assert [y for _, y in points] == pytest.approx(MM)


def test_the_sweep_results_show_asd_in_mm(tmp_path):
    from spread.experiments.sweep import mark_best, parse_arguments, read_results_csv, write_results

    plan = parse_arguments(["ckpt=c", "data.root=/d", "guidance=refine", "guidance.collision=0.0,0.0075",
                            f"out_dir={tmp_path}", "metric=asd", "mode=min"])
    rows = [{"guidance.collision": w, **{k: r[k] for k in ("grecall", "col_mesh", "asd", "stability")}, "point": p}
            for w, r, p in zip((0.0, 0.0075), ROWS, "ab")]
    csv_path, md_path = write_results(rows, tmp_path, plan, mark_best(rows, "asd", "min"))
    assert [r["asd_mm"] for r in read_results_csv(csv_path)] == pytest.approx(MM)
    md = md_path.read_text()
    assert "ASD (mm)" in md and "| **2.1** |" in md and "Best: a (ASD (mm) = 2.1)" in md and "0.0021" not in md


def test_spread_report_shows_asd_in_mm_in_its_files_and_page(tmp_path):
    from spread.reporting.report import run_report
    from spread.reporting.tables import read_csv

    for name, row, weight in (("a", ROWS[0], 0.0), ("b", ROWS[1], 0.0075)):
        folder = tmp_path / "runs" / name
        (folder / ".hydra").mkdir(parents=True)
        (folder / ".hydra" / "config.yaml").write_text(json.dumps({"guidance": {"mode": "refine",
                                                                                "collision": weight}}))
        (folder / "metrics.json").write_text(json.dumps({k: v for k, v in row.items() if k not in ("variant",)}))
    result = run_report([str(tmp_path / "runs")], tmp_path / "report")
    assert [r["asd_mm"] for r in read_csv(result.tables["csv"])] == pytest.approx(MM)
    assert "ASD (mm)" in result.tables["md"].read_text()
    assert [y for _, y in result.plots[("asd", "guidance.collision")][1]] == pytest.approx(MM)
    page = (tmp_path / "report" / "report.html").read_text()
    assert "<th>ASD (mm) ↓</th>" in page and "<td>2.1</td>" in page and "<td>4.2</td>" in page


def logged_table(folder: Path, key: str) -> dict:
    (path,) = (folder / "media" / "table").glob(f"{key}_*.table.json")
    return json.loads(path.read_text())


def test_wandb_tables_show_asd_in_mm(tmp_path, monkeypatch):
    from spread.experiments.compare import log_table1
    from spread.reporting.tables import columns_of
    from spread.reporting.wandb_table import log_ablation
    from spread.tracking.loggers import LoggerConfig

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    ablation = logged_table(Path(log_ablation(ROWS, None, tmp_path / "a", LoggerConfig(mode="offline"))), "ablation")
    column = ablation["columns"].index("asd_mm")
    assert [row[column] for row in ablation["data"]] == pytest.approx(MM) and "asd" not in ablation["columns"]
    rows = [{**r, "method_key": r["variant"]} for r in ROWS]
    table1 = logged_table(Path(log_table1(rows, columns_of(rows), tmp_path / "c", LoggerConfig(mode="offline"))),
                          "table1")
    assert [row[table1["columns"].index("asd_mm")] for row in table1["data"]] == pytest.approx(MM)


def test_the_evaluations_per_scene_wandb_table_shows_asd_in_mm(tmp_path, monkeypatch):
    from spread.tracking.evaluation_wandb import log_metrics
    from spread.tracking.loggers import LoggerConfig, init_run, run_folder

    monkeypatch.setenv("WANDB_MODE", "offline")
    monkeypatch.setenv("WANDB_SILENT", "true")
    metrics = {**ROWS[0], "protocol": {"metrics": ["asd", "stability"]}, "fid_status": "disabled"}
    records = [{"scene_id": "s0", "num_objects": 3, "asd": 0.0021, "stability": 0.9, "still_fraction": 1.0}]
    run = init_run(LoggerConfig(mode="offline"), "evaluate", tmp_path, {})
    folder = Path(run_folder(run))
    log_metrics(run, metrics, records, [])
    run.finish()
    table = logged_table(folder, "per_scene")
    assert table["columns"][2:] == ["num_objects", "asd_mm", "stability", "still_fraction", "error"]
    assert table["data"][0][3] == pytest.approx(2.1)


def test_the_console_tables_show_asd_in_mm(capsys):
    from rich.console import Console

    from spread.cli.demo import comparison_table
    from spread.commands.evaluate import print_evaluation_summary

    metrics = {**ROWS[0], "protocol": {"metrics": ["grecall", "col_mesh", "asd", "stability"]}, "n_evaluated": 4,
               "n_failed": 0, "n_objects": 20, "run": {"seconds": 1.0}, "fid_status": "disabled", "failed": []}
    print_evaluation_summary(metrics, "out")
    printed = capsys.readouterr().out
    assert "ASD (mm)" in printed and "2.1" in printed and "[1.9, 2.5]" in printed and "0.0021" not in printed
    console = Console(record=True, width=200)
    console.print(comparison_table(metrics, {**metrics, "asd": 0.0042}, "demo"))
    text = console.export_text()
    assert "ASD (mm)" in text and "2.1 ± 0.3" in text and "4.2" in text


def test_the_docs_show_asd_in_mm():
    root = Path(__file__).resolve().parents[1]
    docs = [root / "README.md", *(root / "docs").glob("*.md"), root / "benchmarks" / "RESULTS.md"]
    metres = re.compile(r"ASD[^|\n]{0,20}\((m|metres)\)|ASD \(m\)")
    found = [f"{p.name}: {m.group(0)}" for p in docs for m in metres.finditer(p.read_text())]
    assert not found, found


def test_the_trackers_log_a_values_bounds_and_sd_over_seeds_in_its_display_unit_and_read_them_back():
    """A seeded row's ``asd_sd`` went to MLflow in metres beside ``asd_mm`` in millimetres."""
    from spread.metrics.registry import in_display_units, in_stored_units

    stored = {"asd": 0.012, "asd_lo": 0.011, "asd_hi": 0.013, "asd_sd": 0.002, "grecall_sd": 0.1}
    shown = in_display_units(stored)
    assert shown == pytest.approx({"asd_mm": 12.0, "asd_mm_lo": 11.0, "asd_mm_hi": 13.0, "asd_mm_sd": 2.0,
                                   "grecall_sd": 0.1})
    assert in_stored_units(shown) == pytest.approx(stored)


def test_a_setting_is_named_by_its_last_part_on_a_plot_unless_another_ends_alike():
    from spread.reporting.plots import short_name

    keys = ["guidance.collision", "seed", "protocol.seed"]
    assert [short_name(k, keys) for k in keys] == ["collision", "seed", "protocol.seed"]
    assert short_name("protocol.seed", ["protocol.seed"]) == "seed" and short_name("guidance.collision") == "collision"
