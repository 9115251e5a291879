"""The analysis section ``spread-report`` adds for a sweep folder (``results.csv`` + ``points/``), through the one
table writer (:func:`spread.reporting.tables.write_tables`; every metric in its display unit):

* ``analysis_importance.{md,csv}``: per swept setting, the share of each metric's variance over the runs its
  levels explain (one-way η², :func:`spread.results.importance`), largest first by the sweep's first metric;
* ``analysis_pareto.{md,csv}``: the Pareto front of Col_mesh (↓) against GRecall (↑) (:func:`spread.results.pareto`);
* ``analysis_seeds.{md,csv}`` (a sweep with several seeds per point): per point, each metric's mean over its
  seeds ± the 95 % Student-t interval, n seeds (:func:`spread.results.over_seeds`);
* ``analysis_stopped.{md,csv}`` (a training sweep with a trial scheduler): the trials stopped early and the step
  (:func:`spread.results.stopped_trials`);
* ``analysis_compare.{md,csv}`` (``compare=[A,B]``: two point folders under ``points/``, or patterns matching
  one folder per seed): the paired difference A − B on the same graphs and seeds with its bootstrap interval
  (:func:`spread.results.paired_difference`).

``analysis.md`` holds them all; :func:`analysis_section` returns the HTML fragment for ``report.html`` as well.
"""

from __future__ import annotations

import html
from pathlib import Path
from typing import Callable, Sequence

import pandas as pd

#: The metrics the section analyses, where the sweep has them (x and y of the Pareto front first).
METRICS = ("grecall", "col_mesh", "asd", "stability")


def is_sweep_folder(path) -> bool:
    return Path(path, "results.csv").is_file() and Path(path, "points").is_dir()


def records(df: pd.DataFrame) -> list[dict]:
    """A frame's rows as records (NaN as None, as the table writer expects)."""
    return [{k: (None if isinstance(v, float) and v != v else v) for k, v in r.items()}
            for r in df.astype(object).to_dict("records")]


def metric_col(key: str):
    from spread.metrics.registry import value_spec
    from spread.reporting.tables import Column, metric_column

    spec = value_spec(key)
    return metric_column(spec) if spec is not None else Column(key, key, 4)


def point_folders(points: Path, name: str) -> list[Path]:
    """The point folders ``name`` names under ``points/`` (a folder name, or a pattern: one folder per seed)."""
    found = sorted(points.glob(name)) if any(c in name for c in "*?[") else [points / name]
    found = [p for p in found if p.is_dir()]
    if not found:
        raise ValueError(f"compare: {name}: no point folder under {points}")
    return found


def analysis_section(sweep: str | Path, out_dir: str | Path, compare: Sequence[str] | None = None,
                     resamples: int = 1000, seed: int = 0) -> dict:
    """Write the section's tables for sweep folder ``sweep`` into ``out_dir`` (module docstring); returns
    ``{"md": path, "html": fragment, "tables": {name: path}}``."""
    from spread.reporting.tables import Column, write_tables
    from spread.results import importance, load, over_seeds, paired_difference, pareto, stopped_trials
    from spread.results.frame import swept_settings

    sweep, out = Path(sweep), Path(out_dir)
    df = load(sweep)
    metrics = [m for m in METRICS if m in df.columns and pd.to_numeric(df[m], errors="coerce").notna().any()]
    swept = swept_settings(df)  # the seed and an evaluation seed following it are not ranked
    parts, fragments, tables = [f"# Analysis of sweep {sweep.name} ({len(df)} runs)"], [], {}

    def add(name: str, title: str, rows: list[dict], columns: list, note: str = "") -> None:
        paths = write_tables(rows, columns, out / f"analysis_{name}", caption=f"## {title}", formats=("md", "csv"),
                             note=note)
        tables[f"analysis_{name}"] = paths["md"]
        tables[f"analysis_{name}_csv"] = paths["csv"]
        from spread.reporting.tables import html_table, markdown_table

        parts.append(f"## {title}\n\n{markdown_table(rows, columns)}" + (f"\n{note}" if note else ""))
        fragments.append(f"<h3>{html.escape(title)}</h3>{html_table(rows, columns)}"
                         + (f'<p class="note">{html.escape(note)}</p>' if note else ""))

    if metrics and swept:
        ranked = {m: importance(df, m, swept).set_index("setting")["eta_squared"] for m in metrics}
        rows = [{"setting": k, **{f"eta_{m}": float(ranked[m].get(k, float("nan"))) for m in metrics}} for k in swept]
        rows.sort(key=lambda r: -(r[f"eta_{metrics[0]}"] if r[f"eta_{metrics[0]}"] == r[f"eta_{metrics[0]}"] else -1))
        add("importance", "Parameter importance (η²: share of the variance over the runs its values explain)", rows,
            [Column("setting", "setting"), *[Column(f"eta_{m}", f"η² {metric_col(m).label}", 3) for m in metrics]],
            "One-way: each setting alone, interactions not separated.")
    if {"col_mesh", "grecall"} <= set(metrics):
        front = pareto(df, x="col_mesh", y="grecall")
        add("pareto", "Pareto front: Col_mesh ↓ vs GRecall ↑", records(front),
            [Column("point", "point"), *[Column(k, k) for k in swept], metric_col("col_mesh"), metric_col("grecall")])
    seeded = [over_seeds(df, m) for m in metrics] if "seed" in df.columns and metrics else []
    if seeded and seeded[0]["n_seeds"].max() > 1:  # one table: the groups are the same for every metric
        merged = seeded[0].drop(columns=["seeds"])
        for m, table in zip(metrics[1:], seeded[1:]):
            merged = merged.assign(**{k: table[k].to_numpy() for k in (m, f"{m}_lo", f"{m}_hi", f"{m}_sd")})
        keys = seeded[0].attrs["settings"]
        add("seeds", "Per point over seeds (mean ± 95 % Student-t interval over seeds)", records(merged),
            [*[Column(k, k) for k in keys], *[metric_col(m) for m in metrics], Column("n_seeds", "seeds")],
            "± is half the width of the t interval over the point's seeds (scenes pooled within each run).")
    stopped = stopped_trials(sweep)
    if not stopped.empty:
        given = [c for c in stopped.columns if c not in ("trial", "trial_id", "step", "stopped", "failed", "point",
                                                         "reports")]
        add("stopped", f"Trials stopped early ({len(stopped)})", records(stopped),
            [Column("trial", "trial"), Column("step", "stopped at step"), *[Column(c, c) for c in given[:6]]])
    if compare:
        check_compare(sweep, compare)
        a, b = (point_folders(sweep / "points", str(n)) for n in compare)
        rows = []
        for m in metrics:
            try:
                d = paired_difference(a if len(a) > 1 else a[0], b if len(b) > 1 else b[0], m, resamples, seed)
            except ValueError as exc:
                if "no scene with a per-scene" in str(exc):
                    continue  # a metric the points' per_scene.jsonl do not carry
                raise
            rows.append({"metric": metric_col(m).label, "diff": d["diff"], "diff_lo": d["lo"], "diff_hi": d["hi"],
                         "a": d["a"], "b": d["b"], "n_pairs": d["n_pairs"], "scale": metric_col(m).scale})
        shown = [{**r, **{k: r[k] * r["scale"] for k in ("diff", "diff_lo", "diff_hi", "a", "b")}} for r in rows]
        add("compare", f"Paired difference {compare[0]} − {compare[1]} (same graphs and seeds)", shown,
            [Column("metric", "metric"), Column("a", "A", 3), Column("b", "B", 3), Column("diff", "A − B", 3),
             Column("n_pairs", "pairs")],
            f"± is half the width of the 95 % bootstrap interval over the {rows[0]['n_pairs'] if rows else 0} "
            f"paired scenes ({resamples} resamples, seed {seed}); values in display units.")
    md = out / "analysis.md"
    from spread.io import write_text_atomic

    write_text_atomic(md, "\n\n".join(parts) + "\n")
    fragment = f"<h2>Analysis of sweep {html.escape(sweep.name)}</h2>" + "".join(fragments)
    return {"md": md, "html": fragment, "tables": {"analysis": md, **tables}}


def report_analysis(entries: Sequence[str], compare: Sequence[str] | None = None) -> Callable | None:
    """What ``spread-report`` calls with its ``out_dir`` (:func:`spread.reporting.report.run_report`'s
    ``analysis``) when ``runs`` names one sweep folder; None otherwise (``compare`` then is an error)."""
    sweeps = [Path(e) for e in entries if is_sweep_folder(e)]
    if len(sweeps) != 1:
        if compare:
            raise ValueError(f"compare: needs runs= to name one sweep folder (results.csv + points/), got {list(entries)}")
        return None
    if compare:  # said before the report writes anything
        check_compare(sweeps[0], compare)
    return lambda out_dir: analysis_section(sweeps[0], out_dir, compare)


def check_compare(sweep: Path, compare: Sequence[str]) -> None:
    """``compare`` names two points of ``sweep`` that share no run (A − B of a point against itself is 0 with an
    interval of width 0: no comparison), else a ``ValueError`` naming them."""
    if len(compare) != 2:
        raise ValueError(f"compare: expected two points [A,B], got {list(compare)}")
    a, b = (point_folders(Path(sweep) / "points", str(n)) for n in compare)
    both = sorted(set(a) & set(b))
    if both:
        raise ValueError(f"compare: {compare[0]!r} and {compare[1]!r} both name {', '.join(p.name for p in both)}; "
                         f"name two points that share no run")
