"""PNG plots of result records (matplotlib, Agg backend: no display needed).

* :func:`ablation_bars`: one panel per metric, one bar per variant (the ablation table as a figure).
* :func:`metric_vs_weight`: one metric against one guidance weight over a sweep's runs (every run a
  point; the line joins the mean at each weight value, i.e. the marginal effect over the other weights).

Every value is drawn in its column's display unit (:meth:`~spread.reporting.tables.Column.display`: ASD in
mm, as the axis label says). Each function returns what it drew, so callers (and tests) can check the figure's
data.
"""

from __future__ import annotations

import math
import textwrap
from collections import defaultdict
from pathlib import Path
from typing import Sequence

from spread.reporting.tables import Column
from spread.io import atomic_path


def number(value) -> float | None:
    """A finite float, or None (missing, null, NaN, not a number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return None if math.isnan(float(value)) or math.isinf(float(value)) else float(value)


def figure(nrows: int = 1, ncols: int = 1, squeeze: bool = True, **kwargs):
    """``(fig, axes)`` like ``plt.subplots``, but a standalone Agg figure: pyplot's backend and figure list are
    never touched, so drawing files from a notebook leaves its inline plots alone."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    subplot_kw = kwargs.pop("subplot_kw", None)
    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, squeeze=squeeze, subplot_kw=subplot_kw)


def save(fig, path: str | Path, dpi: int = 110) -> Path:
    """Write the figure atomically (no pyplot involved)."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format="png")
    return Path(path)


def shown(column: Column, value) -> float | None:
    """A stored value in the column's display unit (a finite float), or None for a missing or invalid one (not
    finite, outside the column's bounds: :meth:`~spread.reporting.tables.Column.valid`)."""
    v = column.valid(value)
    return None if v is None else number(column.display(v))


def readable_axes(ax, xs: Sequence[float] | None = None, ys: Sequence[float] | None = None) -> None:
    """Numeric axes (those given values; an axis given None is left alone) a reader can read whatever the data:
    plain tick labels (no ``1e-3 +`` offset, no ``×10⁻³`` corner text), at most five ticks, and a span around a
    single value (one point, or every point equal) instead of a hair-thin autoscale."""
    from matplotlib.ticker import MaxNLocator, ScalarFormatter

    for axis, values, set_lim in ((ax.xaxis, xs, ax.set_xlim), (ax.yaxis, ys, ax.set_ylim)):
        if values is None:
            continue
        values = [v for v in values if v is not None]
        if values and min(values) == max(values):
            v = values[0]
            pad = abs(v) * 0.1 if v else 1.0
            set_lim(v - pad, v + pad)
        formatter = ScalarFormatter(useOffset=False)
        formatter.set_scientific(False)
        axis.set_major_formatter(formatter)
        axis.set_major_locator(MaxNLocator(5))


def error_bars(records: Sequence[dict], column: Column, values: list) -> list[list[float]] | None:
    """(below, above) error lengths per bar, display units: the sd across seeds (``<key>_sd``) where rows have
    it, else the bootstrap interval (``<key>_lo`` / ``<key>_hi``); None when no row has either."""
    below, above, found = [], [], False
    key = column.key
    for r, v in zip(records, values):
        sd, lo, hi = (shown(column, r.get(f"{key}_{b}")) for b in ("sd", "lo", "hi"))
        if v is not None and sd is not None:
            below.append(sd), above.append(sd)
            found = True
        elif v is not None and lo is not None and hi is not None:
            below.append(max(0.0, v - lo)), above.append(max(0.0, hi - v))
            found = True
        else:
            below.append(0.0), above.append(0.0)
    return [below, above] if found else None


def short_name(key: str, among: Sequence[str] = ()) -> str:
    """A setting's name on a plot: its last dotted part (``guidance.collision`` → ``collision``), or the whole key
    where another key ``among`` ends alike (``protocol.seed`` beside ``seed``: both read "seed")."""
    tail = key.split(".")[-1]
    return key if any(k != key and k.split(".")[-1] == tail for k in among) else tail


def tick_label(name: str, width: int = 18) -> str:
    """A bar's label on at most two lines of ``width`` characters, broken at spaces (a longer one ends in "…")."""
    lines = textwrap.wrap(name, width) or [""]
    return "\n".join(lines) if len(lines) <= 2 else "\n".join([lines[0], lines[1][:width - 1] + "…"])


def ablation_bars(records: Sequence[dict], columns: Sequence[Column], path: str | Path, label_key: str = "variant",
                  title: str = "") -> dict[str, list[float | None]]:
    """Bar plot: a panel per metric column, a bar per record (``n/a`` where the value is null), with error bars
    (:func:`error_bars`), in display units. Returns metric key → the values drawn, in record order
    (``<key>:error``: the [below, above] error lengths per bar, or None)."""
    fig, axes = figure(1, len(columns), figsize=(2.6 * len(columns), 3.2), squeeze=False)
    names = [str(r.get(label_key)) for r in records]
    colours = ["#8c8c8c", "#4c72b0", "#dd8452", "#55a868", "#c44e52", "#8172b3", "#937860"]
    drawn = {}
    for ax, column in zip(axes[0], columns):
        values = [shown(column, r.get(column.key)) for r in records]
        drawn[column.key] = values
        heights = [0.0 if v is None else v for v in values]
        errors = error_bars(records, column, values)
        bars = ax.bar(range(len(names)), heights, color=[colours[i % len(colours)] for i in range(len(names))],
                      yerr=errors, capsize=3 if errors is not None else 0, ecolor="#333333")
        drawn[f"{column.key}:error"] = None if errors is None else [list(e) for e in zip(*errors)]
        for bar, v in zip(bars, values):
            ax.annotate("n/a" if v is None else f"{v:.{column.digits or 3}f}",
                        (bar.get_x() + bar.get_width() / 2, bar.get_height()),
                        ha="center", va="bottom", fontsize=7)
        if all(v is None for v in values):
            ax.set_ylim(0, 1)
            ax.set_yticks([])
        ax.set_xticks(range(len(names)), [tick_label(n) for n in names], rotation=30,
                      ha="right", rotation_mode="anchor", fontsize=8)
        ax.set_title(column.label + column.arrow, fontsize=9)
        ax.tick_params(axis="y", labelsize=7)
        ax.margins(y=0.15)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    save(fig, path)
    return drawn


def series(records: Sequence[dict], keys: Sequence[str]) -> dict[tuple, list[dict]]:
    """The records grouped by their values of ``keys`` (runs alike in every other setting that differs), in
    first-appearance order."""
    groups: dict[tuple, list[dict]] = {}
    for r in records:
        groups.setdefault(tuple(str(r.get(k)) for k in keys), []).append(r)
    return groups


def metric_vs_weight(records: Sequence[dict], metric: Column, weight: str, path: str | Path, note: str = "",
                     others: Sequence[str] = ()) -> list[tuple[float, float]]:
    """Scatter of ``metric`` (display unit) against the setting ``weight`` over the records that have both, one
    line per series of runs alike in every setting of ``others`` (the other settings that differ: runs of other
    identities are never averaged; repeated runs of one identity are, at their x). Returns the points drawn
    (sorted by the setting, then value)."""
    have = [r for r in records if number(r.get(weight)) is not None and shown(metric, r.get(metric.key)) is not None]
    points = sorted((number(r.get(weight)), shown(metric, r.get(metric.key))) for r in have)
    fig, ax = figure(figsize=(4.6, 3.4))
    if points:
        others = [k for k in others if k != weight]
        for n, (values, rows) in enumerate(series(have, others).items()):
            by_x = defaultdict(list)
            for r in rows:
                by_x[number(r.get(weight))].append(shown(metric, r.get(metric.key)))
            xs = sorted(by_x)
            name = ", ".join(f"{short_name(k, [weight, *others])}={v}" for k, v in zip(others, values)) or "runs"
            colour = f"C{n % 10}"
            ax.scatter([x for x in xs for _ in by_x[x]], [v for x in xs for v in by_x[x]], s=18, alpha=0.6,
                       color=colour)
            ax.plot(xs, [sum(by_x[x]) / len(by_x[x]) for x in xs], "-o", color=colour, ms=4, label=name[:48])
        ax.legend(fontsize=6)
    else:
        ax.text(0.5, 0.5, "no values" + (f"\n{note}" if note else ""), ha="center", va="center", fontsize=8,
                transform=ax.transAxes, wrap=True)
    readable_axes(ax, [x for x, _ in points], [y for _, y in points])
    ax.tick_params(axis="x", labelrotation=30, labelsize=7)
    ax.set_xlabel(weight)
    ax.set_ylabel(metric.label + metric.arrow)
    ax.set_title(f"{metric.label} vs {short_name(weight, [weight, *others])} (n = {len(points)})", fontsize=9)
    fig.tight_layout()
    save(fig, path)
    return points
