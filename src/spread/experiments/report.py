"""``spread-report``: run folders and wandb offline runs → a comparison table and metric-vs-weight plots.

Writes into ``out_dir``:

* ``report.md`` / ``report.csv``: one row per run (name, the guidance weights, GRecall, Col_mesh, ASD in
  metres, Stability, FID, scene count, where it was read from), each metric with its 95 % bootstrap interval
  over scenes (value ± half-width; :mod:`spread.experiments.intervals`); the CSV keeps full precision and the
  bounds (``<metric>_lo``, ``<metric>_hi``) and the bootstrap's seed.
* ``plots/<metric>_vs_<weight>.png``: each metric against each weight, every run a point, the mean per
  weight value joined (:func:`spread.experiments.plots.metric_vs_weight`).
* ``report.html``: one self-contained page (:mod:`spread.experiments.html_report`): training curves of the
  training runs among ``runs``, the table, metric-vs-weight plots with interval bars and labelled points,
  parallel coordinates, per-room-type tables and a grid of the same test graph rendered by each run;
  ``training.csv`` (and a section of ``report.md``): each training run's last logged values.
* ``report.json``: what was read, what was skipped (unfinished runs) and the plots with their points.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

from spread.experiments.intervals import table_note
from spread.experiments.plots import metric_vs_weight
from spread.experiments.runs import read_runs
from spread.experiments.tables import Column, columns_of, metric_column, write_tables
from spread.io import read_text_checked, write_json_atomic

#: The guidance weights of DESIGN §5's sweeps, as config keys.
WEIGHTS = ("guidance.collision", "guidance.gravity", "guidance.relation")


@dataclass
class ReportResult:
    """records: one per run; plots: (metric, weight) → (png path, points drawn); tables: format → path;
    unfinished: run folders without metrics.json that were skipped."""

    records: list[dict]
    plots: dict[tuple[str, str], tuple[Path, list]] = field(default_factory=dict)
    tables: dict[str, Path] = field(default_factory=dict)
    unfinished: list[Path] = field(default_factory=list)
    html: dict = field(default_factory=dict)


def report_columns(weights: Sequence[str], metrics: Sequence[Column]) -> list[Column]:
    return [Column("run", "run"), *[Column(w, w.split(".")[-1], None) for w in weights], *metrics,
            Column("n_scenes", "scenes", None)]


def metric_columns(keys: Sequence[str] | None) -> list[Column]:
    """The columns of the registered metrics (and FID, KID) named by ``keys`` (None: every registered metric and
    FID, KID), each in its display unit."""
    from spread.metrics.registry import SET_METRICS, all_metrics, display_spec

    if keys is None:
        return [metric_column(s) for s in [*all_metrics(), *SET_METRICS]]
    unknown = [k for k in keys if display_spec(k) is None]
    if unknown:
        known = [s.name for s in [*all_metrics(), *SET_METRICS]]
        raise ValueError(f"metrics: unknown {unknown} (choose from {known})")
    return [metric_column(display_spec(k)) for k in keys]


def plot_name(metric: str, weight: str, weights: Sequence[str]) -> str:
    short = weight.split(".")[-1]
    if sum(w.split(".")[-1] == short for w in weights) > 1:
        short = weight.replace(".", "_")
    return f"{metric}_vs_{short}.png"


def run_report(runs, out_dir: str | Path, weights: Sequence[str] = WEIGHTS, metrics: Sequence[str] | None = None,
               title: str = "") -> ReportResult:
    """Read ``runs`` (paths, globs, sweep folders; :func:`~spread.experiments.runs.find_runs`) and write the
    report (module docstring) into ``out_dir``."""
    from spread.experiments.html_report import training_folders, write_html, write_training_tables

    out = Path(out_dir)
    training, runs = training_folders([str(runs)] if isinstance(runs, (str, Path)) else [str(r) for r in runs])
    records, unfinished = read_runs(runs, weights) if runs or not training else ([], [])
    columns = metric_columns(metrics) if metrics is not None else columns_of(records)
    result = ReportResult(records, unfinished=unfinished)
    if records or not training:
        result.tables = write_tables(records, report_columns(weights, columns), out / "report",
                                     caption=title or f"{len(records)} runs", formats=("md", "csv"),
                                     note=table_note(records))
    if training:
        result.tables |= write_training_tables(training, out / "report", append=bool(records))
    fid_notes = sorted({str(r.get("fid_status")) for r in records if r.get("fid") is None and r.get("fid_status")})
    for metric in columns if records else []:
        for weight in weights:
            path = out / "plots" / plot_name(metric.key, weight, weights)
            note = "; ".join(fid_notes)[:200] if metric.key == "fid" else ""
            result.plots[(metric.key, weight)] = (path, metric_vs_weight(records, metric, weight, path, note))
    result.tables["html"] = out / "report.html"
    result.html = write_html(out / "report.html", title or f"spread-report: {len(records)} evaluated runs, "
                             f"{len(training)} training runs", training, records, columns, weights,
                             note=table_note(records) if records else "")
    write_json_atomic(out / "report.json", {
        "training_runs": [str(p) for p in training], "html": str(out / "report.html"),
        "runs": [{"run": r["run"], "source": r["source"], "kind": r["kind"]} for r in records],
        "unfinished": [str(p) for p in unfinished],
        "refused": result.html.get("refused", []),
        "tables": {k: str(v) for k, v in result.tables.items()},
        "plots": [{"metric": m, "weight": w, "png": str(p), "points": pts}
                  for (m, w), (p, pts) in result.plots.items()],
    })
    return result


def runs_argument(value) -> list[str]:
    """``runs`` as a list of strings (a single path or glob, or a list of them; a Hydra list node too)."""
    if isinstance(value, (str, Path)):
        return [str(value)]
    return [str(v) for v in value]


def print_report(result: ReportResult) -> None:
    """The report's table and where its files went, on the console."""
    from rich.console import Console

    console = Console()
    if "md" in result.tables:
        console.print(read_text_checked(result.tables["md"]), markup=False)
    for path in result.unfinished:
        console.print(f"[yellow]skipped (no metrics.json yet): {path}[/yellow]")
    for why in result.html.get("refused", []):
        console.print(f"not read: {why}", markup=False, soft_wrap=True)
    console.print(f"{len(result.records)} runs; table {result.tables.get('md')}, {result.tables.get('csv')}; "
                  f"{len(result.plots)} plots in {result.tables['html'].parent / 'plots'}; page {result.tables['html']}")
