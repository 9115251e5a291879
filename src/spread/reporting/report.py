"""``spread-report``: run folders and wandb offline runs → a comparison table and metric-vs-weight plots.

Writes into ``out_dir``:

* ``report.md`` / ``report.csv``: one row per run — its name, **every setting that differs between the runs**
  (from each run's recorded identity, :mod:`spread.reporting.runs`: any guidance term's weight by its name,
  ``guidance.iterations``, the sampler, the seed, the checkpoint, the protocol, ...), each metric in its display
  unit (ASD in mm) with its 95 % bootstrap interval over scenes (value ± half-width;
  :mod:`spread.reporting.intervals`), the scene count; under the table, the settings every run shares. Runs are
  never averaged: two runs that differ in anything are two rows. The CSV keeps full precision, the bounds, the
  bootstrap's seed and each run's ``identity`` (the digest of all its settings).
* ``plots/<metric>_vs_<setting>.png``: each metric against each numeric setting that differs (or the ``weights``
  asked for), every run a point, one line per series of runs alike in every other differing setting
  (:func:`spread.reporting.plots.metric_vs_weight`).
* ``report.html``: one self-contained page (:mod:`spread.reporting.html_report`): training curves of the
  training runs among ``runs``, the table, metric-vs-weight plots with interval bars and labelled points,
  parallel coordinates, per-room-type tables and a grid of the same test graph rendered by each run;
  ``training.csv`` (and a section of ``report.md``): each training run's last logged values.
* ``analysis.md`` and ``analysis_*.{md,csv}`` (a sweep folder, with the section in ``report.html``): parameter
  importance, the Pareto front, intervals over seeds, stopped trials, a paired difference
  (:mod:`spread.results.analysis`).
* ``report.json``: what was read (each run's full settings), what was skipped (unfinished runs) and the plots
  with their points.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

from spread.reporting.intervals import table_note
from spread.reporting.plots import metric_vs_weight
from spread.reporting.runs import read_runs
from spread.reporting.tables import Column, columns_of, metric_column, write_tables
from spread.io import read_text_checked, write_json_atomic


@dataclass
class ReportResult:
    """records: one per run; plots: (metric, setting) → (png path, points drawn); tables: format → path;
    unfinished: run folders without metrics.json that were skipped; settings: the settings that differ (the
    table's setting columns); shared: the settings every run has alike."""

    records: list[dict]
    plots: dict[tuple[str, str], tuple[Path, list]] = field(default_factory=dict)
    tables: dict[str, Path] = field(default_factory=dict)
    unfinished: list[Path] = field(default_factory=list)
    html: dict = field(default_factory=dict)
    settings: list[str] = field(default_factory=list)
    shared: dict = field(default_factory=dict)


def report_columns(settings: Sequence[str], metrics: Sequence[Column]) -> list[Column]:
    return [Column("run", "run"), *[Column(k, k) for k in settings], *metrics, Column("n_scenes", "scenes", None)]


def metric_columns(keys: Sequence[str] | None) -> list[Column]:
    """The columns of the registered values (and FID, KID) named by ``keys`` (None: every registered metric's and
    FID, KID), each in its display unit."""
    from spread.metrics.registry import METRICS, display_values, value_spec

    if keys is None:
        return [metric_column(v) for v in display_values(METRICS.names()) if v.shown]
    unknown = [k for k in keys if value_spec(k) is None]
    if unknown:
        known = [v.name for v in display_values(METRICS.names())]
        raise ValueError(f"metrics: unknown {unknown} (choose from {known})")
    return [metric_column(value_spec(k)) for k in keys]


def plot_name(metric: str, setting: str, settings: Sequence[str]) -> str:
    short = setting.split(".")[-1]
    if sum(w.split(".")[-1] == short for w in settings) > 1:
        short = setting.replace(".", "_")
    return f"{metric}_vs_{short}.png"


def numeric(records: Sequence[dict], key: str) -> bool:
    values = [r["settings"].get(key) for r in records if r["settings"].get(key) is not None]
    return bool(values) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def shared_settings(records: Sequence[dict], differ: Sequence[str]) -> dict:
    """The settings every run has, alike (what the table does not repeat per row)."""
    if not records:
        return {}
    first = records[0]["settings"]
    return {k: v for k, v in first.items() if k not in differ and all(k in r["settings"] for r in records)}


def run_report(runs, out_dir: str | Path, weights: Sequence[str] | None = None, metrics: Sequence[str] | None = None,
               title: str = "", analysis: Callable[[Path], dict] | None = None) -> ReportResult:
    """Read ``runs`` (paths, globs, sweep folders; :func:`~spread.reporting.runs.find_runs`) and write the
    report (module docstring) into ``out_dir``; ``weights``: the settings plotted on the x axis (None: every
    numeric setting that differs between the runs); ``analysis``: called with ``out_dir``, writes more tables
    and returns ``{"html": fragment, "tables": {name: path}}`` for the page (a sweep's analysis section,
    :mod:`spread.results.analysis`, handed in by the command)."""
    from spread.reporting.html_report import training_folders, write_html, write_training_tables
    from spread.reporting.runs import name_differences

    out = Path(out_dir)
    earlier = earlier_outputs(out)
    training, runs = training_folders([str(runs)] if isinstance(runs, (str, Path)) else [str(r) for r in runs])
    records, unfinished = read_runs(runs) if runs or not training else ([], [])
    differ = name_differences(records)  # every differing setting named per run
    axes = list(weights) if weights is not None else [k for k in differ if numeric(records, k)]
    shown = [*differ, *[k for k in axes if k not in differ]]
    for r in records:
        r.update({k: r["settings"].get(k) for k in axes})
    columns = metric_columns(metrics) if metrics is not None else columns_of(records)
    shared = shared_settings(records, differ)
    result = ReportResult(records, unfinished=unfinished, settings=shown, shared=shared)
    same = ("Every run: " + ", ".join(f"{k}={v}" for k, v in shared.items()) + ".") if shared else ""
    if records or not training:
        keys = ["run", *shown, *[c.key for c in columns], "n_scenes", "identity", "source", "kind"]
        result.tables = write_tables(records, report_columns(shown, columns), out / "report",
                                     caption=title or f"{len(records)} runs", formats=("md", "csv"),
                                     note=table_note(records), md_extra=same,
                                     csv_keys=list(dict.fromkeys([*keys, *[k for r in records for k in r
                                                                           if k != "settings"]])))
    if training:
        result.tables |= write_training_tables(training, out / "report", append=bool(records))
    fid_notes = sorted({str(r.get("fid_status")) for r in records if r.get("fid") is None and r.get("fid_status")})
    for metric in columns if records else []:
        for axis in axes:
            path = out / "plots" / plot_name(metric.key, axis, axes)
            note = "; ".join(fid_notes)[:200] if metric.key == "fid" else ""
            result.plots[(metric.key, axis)] = (path, metric_vs_weight(records, metric, axis, path, note, differ))
    extra = analysis(out) if analysis is not None else {}
    result.tables |= extra.get("tables") or {}
    result.tables["html"] = out / "report.html"
    result.html = write_html(out / "report.html", title or f"spread-report: {len(records)} evaluated runs, "
                             f"{len(training)} training runs", training, records, columns, shown,
                             note=" ".join(p for p in (table_note(records) if records else "", same) if p),
                             extra=extra.get("html") or "")
    write_json_atomic(out / "report.json", {
        "training_runs": [str(p) for p in training], "html": str(out / "report.html"),
        "runs": [{"run": r["run"], "source": r["source"], "kind": r["kind"], "identity": r["identity"],
                  "settings": r["settings"]} for r in records],
        "differing": shown, "shared": shared,
        "unfinished": [str(p) for p in unfinished],
        "refused": result.html.get("refused", []),
        "tables": {k: str(v) for k, v in result.tables.items()},
        "plots": [{"metric": shown_key(m)[0], "unit": shown_key(m)[1], "setting": w, "png": str(p), "points": pts}
                  for (m, w), (p, pts) in result.plots.items()],  # points in the plot's (display) unit, keyed so
    })
    written = {*result.tables.values(), *(p for p, _ in result.plots.values()), out / "report.json"}
    remove_stale(out, earlier - {Path(p) for p in written})
    return result


def earlier_outputs(out: Path) -> set[Path]:
    """The files an earlier report in ``out`` recorded writing (its ``report.json``'s tables and plots; none when
    it does not read)."""
    from spread.io import read_json_object

    try:
        record = read_json_object(out / "report.json") if (out / "report.json").is_file() else {}
    except (OSError, ValueError):
        return set()
    tables = record.get("tables") if isinstance(record.get("tables"), dict) else {}
    plots = record.get("plots") if isinstance(record.get("plots"), list) else []
    named = [*tables.values(), *(p.get("png") for p in plots if isinstance(p, dict))]
    return {Path(p) for p in named if isinstance(p, str)}


def remove_stale(out: Path, paths: set[Path]) -> None:
    """Remove what an earlier report in ``out`` wrote and this one did not (its plots of other runs, a table this
    report has no rows for), so the folder shows this report alone: only files directly in ``out`` or its
    ``plots/``, named as a report names them, never through a link (a hand-edited ``report.json`` names nothing
    else)."""
    root = out.resolve()
    for path in paths:
        if path.is_symlink() or not path.is_file():
            continue
        place = path.resolve()
        ours = (place.parent == root and place.name.startswith(("report", "analysis"))) or \
            (place.parent == root / "plots" and place.suffix == ".png")
        if ours:
            place.unlink()


def shown_key(key: str) -> tuple[str, str | None]:
    """(the key a value is shown under, its unit): ``asd`` (metres) is plotted in mm as ``asd_mm``
    (:attr:`spread.metrics.registry.ValueSpec.key`); a value without a unit keeps its key."""
    from spread.metrics.registry import value_spec

    spec = value_spec(key)
    return (spec.key, spec.unit) if spec is not None and spec.unit else (key, None)


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
        console.print(f"[yellow]skipped (no metrics.json yet): {path}[/yellow]", soft_wrap=True)
    for why in result.html.get("refused", []):
        console.print(f"not read: {why}", markup=False, soft_wrap=True)
    html = result.tables["html"]
    tables = ", ".join(str(result.tables[k]) for k in ("md", "csv", "training_csv") if result.tables.get(k))
    console.print(f"{len(result.records)} runs; table {tables}; "
                  f"{len(result.plots)} plots in {html.parent / 'plots'}; page {html}",
                  soft_wrap=True)  # paths are copied from here: never broken across lines
