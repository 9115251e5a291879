"""``spread-report``'s HTML page: one self-contained file (``report.html``; every figure a base64 PNG inside,
no script, no link outside) that a browser opens from disk or from a cluster's file share.

Sections, each drawn only when its runs have the data:

* **training curves**: the training runs' ``csv/version_<n>/metrics.csv`` (every launch of the run, in step
  order), one panel per curve (loss, validation loss and GRecall, learning rate, gradient norm), runs
  overlaid (:func:`training_curves`);
* **table**: the report's table (one row per evaluated run, each metric ± its interval);
* **metric vs setting**: each metric (in its display unit, ASD in mm) against each numeric setting that varies
  over the runs, every run a point with its interval as an error bar and its name beside it; with no varying
  setting, each metric per run (:func:`metric_plot`);
* **parallel coordinates** over the runs (the varying settings, then the metrics in their display units; each
  axis from its min to its max; :func:`parallel_coordinates`);
* **per room type**: each run's ``per_room_type`` breakdown of ``metrics.json``;
* **renders**: the same test graph as rendered by each run (the first render name the runs share).

Every file is read through :func:`spread.io.check_input_file` (a FIFO, a device or a link out of its run folder
is skipped by name, ``held["refused"]``, never opened), and a render is embedded only when it is a PNG (PIL
verifies it) whose real path lies inside its run folder (:func:`embeddable_png`): the page is shared, so it never
carries bytes of any other file.

A **training run folder** is one with ``csv/version_*/metrics.csv`` (Lightning's CSV logger, which
``spread-train`` always writes unless ``logger=none``): :func:`training_folders` picks them out of the
``runs`` argument, the other entries are evaluation runs (:mod:`spread.reporting.runs`).
"""

from __future__ import annotations

import base64
import csv
import glob
import html
import io
import math
from pathlib import Path
from typing import Sequence

from spread.reporting.plots import figure, number, readable_axes, short_name, shown
from spread.reporting.tables import Column, html_table

#: Training curves drawn, in this order (``lr-*`` stands for every learning-rate column).
CURVES = ("train/loss", "val/loss", "val/grecall", "lr-*", "train/grad_norm")


# ---- training runs -------------------------------------------------------------------------------------------

def is_training_run(path: Path) -> bool:
    return path.is_dir() and any(path.glob("csv/version_*/metrics.csv"))


def training_folders(entries: Sequence[str]) -> tuple[list[Path], list[str]]:
    """(training run folders, the other entries): an entry (a path or glob) that is a training run folder goes to
    the first list; a folder with training runs under it (an ablation's, a comparison's) adds them to the first
    list and stays in the second when it also holds evaluated runs. A training run named twice (by two entries, or
    by another spelling of its path) is listed once: its rows were zipped with the wrong runs' curves."""
    training, rest = [], []

    def add(run: Path) -> None:
        if run.resolve() not in {t.resolve() for t in training}:
            training.append(run)

    for entry in entries:
        paths = [Path(p) for p in sorted(glob.glob(entry))] if glob.has_magic(entry) else [Path(entry)]
        for path in paths:
            if is_training_run(path):
                add(path)
                continue
            nested = sorted({m.parents[2] for m in path.rglob("csv/version_*/metrics.csv")}) if path.is_dir() else []
            for run in nested:
                add(run)
            if not nested or any(has_evaluation(m) for m in path.rglob("metrics.json")):
                rest.append(str(path) if glob.has_magic(entry) else entry)
    return training, rest


def has_evaluation(path: Path) -> bool:
    """Whether ``path`` is an evaluation's ``metrics.json`` (whichever registered metrics it selected)."""
    from spread.reporting.runs import is_eval_metrics

    return is_eval_metrics(path)


def read_curves(folder: Path, refused: list | None = None) -> dict[str, list[tuple[float, float]]]:
    """Curve name → (step, value) points of a training run, over all its ``csv/version_<n>`` launches (a file
    :func:`~spread.io.check_input_file` refuses is skipped, and named in ``refused``)."""
    from spread.io import InputFileError, NotUtf8, read_text_checked

    curves: dict[str, dict[float, float]] = {}
    versions = sorted(folder.glob("csv/version_*/metrics.csv"), key=lambda p: version_number(p.parent.name))
    for path in versions:
        try:
            text = read_text_checked(path, root=folder)
        except (InputFileError, OSError, NotUtf8) as exc:
            if refused is not None:
                refused.append(f"{path}: {exc}" if str(path) not in str(exc) else str(exc))
            continue
        for row in csv.DictReader(io.StringIO(text, newline="")):
            step = number(to_float(row.get("step")))
            if step is None:
                continue
            for key, cell in row.items():
                value = number(to_float(cell))
                if key not in ("step", "epoch") and value is not None:
                    curves.setdefault(key, {})[step] = value
    return {k: sorted(v.items()) for k, v in curves.items()}


def version_number(name: str) -> int:
    tail = name.split("_")[-1]
    return int(tail) if tail.isdigit() else -1


def to_float(text):
    try:
        return float(text)
    except (TypeError, ValueError):
        return None


def curve_keys(runs: dict[str, dict]) -> list[str]:
    present = sorted({k for curves in runs.values() for k in curves})
    keys = []
    for pattern in CURVES:
        keys += [k for k in present if (k.startswith(pattern[:-1]) if pattern.endswith("*") else k == pattern)]
    return keys


def training_curves(runs: dict[str, dict]) -> tuple[str | None, list[str]]:
    """(base64 PNG, the curves drawn): a panel per curve of :data:`CURVES`, a line per run."""
    keys = curve_keys(runs)
    if not keys:
        return None, []
    cols = min(3, len(keys))
    rows = math.ceil(len(keys) / cols)
    fig, axes = figure(rows, cols, squeeze=False, figsize=(4.2 * cols, 3.0 * rows))
    for ax, key in zip(axes.flat, keys):
        for name, curves in runs.items():
            points = curves.get(key) or []
            if points:
                ax.plot([p[0] for p in points], [p[1] for p in points], "-" if len(points) > 1 else "o", ms=3,
                        label=name, lw=1.2)
        ax.set_title(key, fontsize=9)
        ax.set_xlabel("step", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    for ax in list(axes.flat)[len(keys):]:
        ax.set_visible(False)
    fig.tight_layout()
    return png(fig), keys


# ---- evaluated runs ------------------------------------------------------------------------------------------

def varying(records: Sequence[dict], key: str) -> bool:
    return len({number(r.get(key)) for r in records if number(r.get(key)) is not None}) > 1


def metric_plot(records: Sequence[dict], metric: Column, weight: str | None,
                among: Sequence[str] = ()) -> tuple[str | None, list]:
    """(base64 PNG, points (x, value, lo, hi, run)): ``metric`` against ``weight`` (None: against the run), each
    run a labelled point with its interval as an error bar."""
    points = []
    for i, r in enumerate(records):
        x = i if weight is None else number(r.get(weight))
        y = shown(metric, r.get(metric.key))
        if x is not None and y is not None:
            points.append((x, y, shown(metric, r.get(f"{metric.key}_lo")), shown(metric, r.get(f"{metric.key}_hi")),
                           str(r["run"])))
    if not points:
        return None, []
    fig, ax = figure(figsize=(4.6, 3.3))
    shared_x = len({x for x, *_ in points}) < len(points)  # names at one x would be written over each other
    for x, y, lo, hi, name in points:
        err = [[max(0.0, y - lo)], [max(0.0, hi - y)]] if lo is not None and hi is not None else None
        ax.errorbar([x], [y], yerr=err, fmt="o", ms=4, capsize=3, color="#4c72b0", ecolor="#8c8c8c")
        if weight is not None and not shared_x and len(points) <= 8:
            ax.annotate(name[:24], (x, y), xytext=(4, 3), textcoords="offset points", fontsize=6)
    if weight is None:
        ax.set_xticks(range(len(records)), [str(r["run"])[:16] for r in records], rotation=30, ha="right",
                      rotation_mode="anchor", fontsize=6)
        ax.set_xlim(-0.5, len(records) - 0.5)
        readable_axes(ax, ys=[y for _, y, *_ in points])
    else:
        readable_axes(ax, [x for x, *_ in points], [y for _, y, *_ in points])
        ax.tick_params(axis="x", labelrotation=30)
        ax.set_xlabel(weight, fontsize=8)
    ax.set_ylabel(metric.label + metric.arrow, fontsize=8)
    ax.set_title(f"{metric.label}" + (f" vs {short_name(weight, among)}" if weight else " per run") +
                 f" (n = {len(points)})", fontsize=9)
    ax.tick_params(labelsize=7)
    ax.margins(x=0.15, y=0.2)
    fig.tight_layout()
    return png(fig), points


def parallel_coordinates(records: Sequence[dict], axes: Sequence[Column]) -> str | None:
    """Base64 PNG: one line per run over the columns ``axes`` (each in its display unit, scaled from its min to its
    max, which are written at its ends), coloured by the last axis's value; None with fewer than 2 runs or axes."""
    axes = [c for c in axes if any(shown(c, r.get(c.key)) is not None for r in records)]
    if len(records) < 2 or len(axes) < 2:
        return None
    values = {c.key: [shown(c, r.get(c.key)) for r in records] for c in axes}
    bounds = {k: (min(v for v in vs if v is not None), max(v for v in vs if v is not None)) for k, vs in values.items()}
    fig, ax = figure(figsize=(1.6 * len(axes) + 1.5, 3.6))
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    colour = axes[-1]
    for n in range(len(records)):
        ys = []
        for c in axes:
            v, (lo, hi) = values[c.key][n], bounds[c.key]
            ys.append(math.nan if v is None else (0.5 if hi == lo else (v - lo) / (hi - lo)))
        v, (lo, hi) = values[colour.key][n], bounds[colour.key]
        ax.plot(range(len(axes)), ys, "-o", ms=3, lw=1.2, alpha=0.8,
                color=cmap(0.5 if v is None or hi == lo else (v - lo) / (hi - lo)))
    for i, c in enumerate(axes):
        ax.axvline(i, color="#444", lw=0.8)
        lo, hi = bounds[c.key]
        ax.annotate(f"{hi:.3g}", (i, 1.0), xytext=(0, 4), textcoords="offset points", ha="center", fontsize=6)
        ax.annotate(f"{lo:.3g}", (i, 0.0), xytext=(0, -10), textcoords="offset points", ha="center", fontsize=6)
    ax.set_xticks(range(len(axes)), [short_name(c.label, [a.label for a in axes]) for c in axes], fontsize=7)
    ax.set_yticks([])
    ax.set_ylim(-0.12, 1.12)
    ax.set_title(f"{len(records)} runs (colour: {colour.label})", fontsize=9)
    fig.tight_layout()
    return png(fig)


def metrics_of(record: dict) -> dict:
    """The run's ``metrics.json`` ({} when it is not a run folder's, or the file is refused or not JSON)."""
    from spread.io import read_json_object

    path = Path(record.get("source", "")) / "metrics.json"
    if record.get("kind") != "folder" or not path.exists():
        return {}
    try:
        return read_json_object(path)
    except (OSError, ValueError):
        return {}


def embeddable_png(path: Path, run: Path) -> str | None:
    """Why ``path`` may not be embedded in the page (None: it may): it must be a regular file whose real path is
    inside the run folder ``run`` (:func:`~spread.io.check_input_file`, and no linked ``renders/`` folder either),
    of plausible size, and a PNG that PIL can verify."""
    from PIL import Image

    from spread.io import InputFileError, check_input_file, read_bytes_checked

    try:
        check_input_file(path, root=run)
        if not path.resolve().is_relative_to(run.resolve()):
            return f"{path}: resolves to {path.resolve()}, outside the run folder {run}; not embedded"
        data = read_bytes_checked(path, root=run)
        if not data.startswith(b"\x89PNG\r\n\x1a\n"):
            return f"{path}: not a PNG file; not embedded"
        with Image.open(io.BytesIO(data)) as image:
            image.verify()
    except InputFileError as exc:
        return f"{exc}; not embedded"
    except Exception as exc:  # PIL's errors for a damaged PNG, an unreadable file
        return f"{path}: not a readable PNG ({type(exc).__name__}: {exc}); not embedded"
    return None


def renders_of(record: dict, refused: list | None = None) -> dict[str, Path]:
    """Render name → PNG of an evaluated run: its own ``renders/``, else its sampling run's; only PNGs inside
    the folder they belong to (:func:`embeddable_png`; the others are named in ``refused``)."""
    folder = Path(record.get("source", ""))
    metrics = metrics_of(record)
    found = {}
    for run in dict.fromkeys((folder, Path(str(metrics.get("scenes") or folder / "x")).parent)):  # each once
        renders = run / "renders"
        if not renders.is_dir():
            continue
        stale = resampled_since(run, metrics)
        if stale:
            if refused is not None:
                refused.append(f"{renders}: not shown: {stale}")
            continue
        for p in sorted(renders.glob("*.png")):
            if p.stem in found:
                continue
            why = embeddable_png(p, run)
            if why is None:
                found[p.stem] = p
            elif refused is not None:
                refused.append(why)
    return found


def resampled_since(run: Path, metrics: dict) -> str | None:
    """Why the renders of sampling folder ``run`` are not of the scenes ``metrics`` measured: its ``sampling.json``
    records other sampling settings than the evaluation's ``sampled_with`` (the folder was sampled again since, with
    its renders); None when they agree or either record is missing (an older run: shown as before)."""
    from spread.io import read_json_object
    from spread.runtime.fingerprint import identity_changes

    made = metrics.get("sampled_with")
    if not isinstance(made, dict) or not (run / "sampling.json").is_file():
        return None
    try:
        pinned = read_json_object(run / "sampling.json").get("fingerprint")
    except (OSError, ValueError):
        return None
    if not isinstance(pinned, dict):
        return None
    changed = identity_changes({k: v for k, v in made.items() if k not in ("samples_per_graph", "evaluation")},
                               pinned)
    return f"sampled again since the evaluation, with other settings ({', '.join(changed[:4])})" if changed else None


def render_grid(records: Sequence[dict], refused: list | None = None) -> tuple[str | None, dict[str, Path]]:
    """(the render name shown, run → its PNG): the first name all runs with renders share, else each run's first
    render."""
    by_run = {str(r["run"]): renders_of(r, refused) for r in records}
    by_run = {k: v for k, v in by_run.items() if v}
    if not by_run:
        return None, {}
    shared = sorted(set.intersection(*[set(v) for v in by_run.values()]))
    if shared:
        return shared[0], {k: v[shared[0]] for k, v in by_run.items()}
    return None, {k: v[sorted(v)[0]] for k, v in by_run.items()}


# ---- the page -------------------------------------------------------------------------------------------

def png(fig) -> str:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    return base64.b64encode(buffer.getvalue()).decode()


def img(data: str, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


STYLE = """body{font-family:system-ui,sans-serif;margin:1.5em;color:#222;max-width:1400px}
h1{font-size:1.4em}h2{font-size:1.15em;margin-top:1.6em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:0.85em;margin:0.5em 0}td,th{border:1px solid #ccc;padding:3px 7px;
text-align:right}th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}
.grid{display:flex;flex-wrap:wrap;gap:10px}figure{margin:0}figcaption{font-size:0.8em;text-align:center}
img{max-width:100%}.grid img{max-width:260px;border:1px solid #ccc}.note{color:#555;font-size:0.85em}"""


def write_html(path: Path, title: str, training: list[Path], records: Sequence[dict], columns: Sequence[Column],
               weights: Sequence[str], md_table: str | None = None, note: str = "", extra: str = "") -> dict:
    """Write the page (module docstring); returns what it holds (section → count) for the caller and tests.
    ``extra``: an HTML fragment placed after the runs' sections (a sweep's analysis)."""
    from spread.io import atomic_path

    parts = [f"<h1>{html.escape(title)}</h1>"]
    held: dict = {"refused": []}
    if training:
        runs = {f.name if f.name not in [g.name for g in training if g != f] else str(f):
                read_curves(f, held["refused"]) for f in training}
        data, keys = training_curves(runs)
        held["training_runs"], held["curves"] = len(runs), keys
        parts.append(f"<h2>Training curves ({len(runs)} runs)</h2>")
        parts.append(img(data, "training curves") if data else "<p>no logged curves</p>")
        rows = [training_row(name, f, c, keys) for (name, c), f in zip(runs.items(), training)]
        parts.append(html_table(rows, training_columns(keys)))
    if records:
        parts.append(f"<h2>Evaluated runs ({len(records)})</h2>")
        parts.append(html_table(records, [Column("run", "run"), *[Column(w, w) for w in weights], *columns,
                                          Column("n_scenes", "scenes")]))
        if note:
            parts.append(f'<p class="note">{html.escape(note)}</p>')
        varied = [w for w in weights if varying(records, w)]
        plots = []
        for c in columns:
            for w in (varied or [None]):
                data, points = metric_plot(records, c, w, varied)
                if data:
                    plots.append(f"<figure>{img(data, f'{c.key} vs {w}')}</figure>")
        held["metric_plots"] = len(plots)
        if plots:
            against = " vs the settings that differ" if varied else " per run"
            parts.append(f"<h2>Metrics{against} (bars: intervals)</h2>")
            parts.append('<div class="grid">' + "".join(plots) + "</div>")
        parallel = parallel_coordinates(records, [*[Column(w, w) for w in varied], *columns])
        held["parallel"] = parallel is not None
        if parallel:
            parts.append("<h2>Parallel coordinates</h2>" + img(parallel, "parallel coordinates"))
        room_rows = [{**m, "run": r["run"], "room_type": room} for r in records
                     for room, m in (metrics_of(r).get("per_room_type") or {}).items()]
        held["room_rows"] = len(room_rows)
        if room_rows:
            parts.append("<h2>Per room type</h2>" + html_table(room_rows, [
                Column("run", "run"), Column("room_type", "room type"), Column("n_evaluated", "scenes"), *columns]))
        name, renders = render_grid(records, held["refused"])
        held["renders"] = len(renders)
        if renders:
            from spread.io import read_bytes_checked

            figures = "".join(f"<figure>{img(base64.b64encode(read_bytes_checked(p)).decode(), run)}"
                              f"<figcaption>{html.escape(run)}</figcaption></figure>" for run, p in renders.items())
            parts.append(f"<h2>Renders: {html.escape(name or 'first render of each run')}</h2>"
                         f'<div class="grid">{figures}</div>')
    if extra:
        parts.append(extra)
    if held["refused"]:
        parts.append("<h2>Files not read</h2><ul>" + "".join(f"<li>{html.escape(why)}</li>"
                                                              for why in held["refused"]) + "</ul>")
    page = (f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
            f"<style>{STYLE}</style></head><body>{''.join(parts)}</body></html>")
    with atomic_path(path) as tmp:
        Path(tmp).write_text(page, encoding="utf-8")
    return held


def training_columns(keys: Sequence[str]) -> list[Column]:
    """The training-runs table's columns: run, the steps trained, each curve's last value."""
    return [Column("run", "run"), Column("steps", "steps", None), *[Column(k, f"last {k}", 4) for k in keys]]


def steps_trained(folder: Path, curves: dict) -> int | None:
    """The optimiser steps a training run made: its ``metrics.json``'s ``global_step`` (what the console said), else
    the last logged step + 1 (a curve's step is the 0-based index of the batch it was logged at)."""
    from spread.io import read_json_object

    try:
        step = read_json_object(Path(folder) / "metrics.json").get("global_step")
    except (OSError, ValueError):
        step = None
    if isinstance(step, int) and not isinstance(step, bool):
        return step
    last = max((p[0] for v in curves.values() for p in v if p[0] is not None), default=None)
    return None if last is None else int(last) + 1


def training_row(name: str, folder: Path, curves: dict, keys: Sequence[str]) -> dict:
    """One training run's row: ``run``, ``source``, ``steps`` (:func:`steps_trained`), each curve's last value."""
    return {"run": name, "source": str(folder), "steps": steps_trained(folder, curves),
            **{k: (curves.get(k) or [(None, None)])[-1][1] for k in keys}}


def training_rows(training: Sequence[Path]) -> tuple[list[str], list[dict]]:
    """(curve keys, one record per training run: :func:`training_row`)."""
    runs = {str(f): read_curves(f) for f in training}
    keys = curve_keys(runs)
    return keys, [training_row(Path(f).name, Path(f), c, keys) for f, c in runs.items()]


def write_training_tables(training: Sequence[Path], stem: Path, append: bool) -> dict[str, Path]:
    """``<stem>_training.csv`` and a "Training runs" section of ``<stem>.md`` (appended when ``append``)."""
    from spread.reporting.tables import markdown_table, write_csv
    from spread.io import write_text_atomic

    keys, rows = training_rows(training)
    columns = training_columns(keys)
    from spread.io import read_text_checked

    md = Path(stem).with_suffix(".md")
    before = read_text_checked(md) + "\n" if append and md.exists() else ""
    write_text_atomic(md, before + f"## Training runs ({len(rows)})\n\n" + markdown_table(rows, columns) + "\n")
    return {"md": md, "training_csv": write_csv(rows, ["run", "steps", *keys, "source"],
                                                Path(f"{stem}_training.csv"))}
