"""The platform's one table writer: result records (one dict per row) as Markdown, CSV, LaTeX, HTML and wandb rows.

A :class:`Column` names a record key, its header label, its display unit and scale, and how a value is printed.
:func:`metric_columns` are the results tables' columns, from the metric registry (:mod:`spread.metrics.registry`:
each value's display unit lives there): every table, CSV, HTML page, wandb table and plot shows a metric in its
registered display unit (ASD in mm; ``metrics.json`` stores metres), the unit in the header — in CSV the header
is ``<key>_<unit>`` (``asd_mm``, ``asd_mm_lo``) and the cell the displayed number at full precision (floats by
``repr``; ``None`` as an empty cell; a unitless value reads back bit for bit). Every table of the platform
(spread-ablate, spread-compare, spread-report, spread-sweep's results, the HTML report, the evaluation's console
table) is written here.

**Confidence intervals.** A record that holds ``<key>_lo`` and ``<key>_hi`` beside ``<key>`` (the bootstrap
interval of :mod:`spread.evaluation.bootstrap`) prints as ``value ± h`` with h half the interval's width,
in the column's digits; CSV keeps both bounds as columns right after the value. ``note`` (what ± means) goes
under the Markdown table and into the LaTeX caption.
"""

from __future__ import annotations

import csv
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

from spread.io import write_text_atomic


@dataclass(frozen=True)
class Column:
    """key: record key; label: header; digits: decimals printed (None: as is); better: "max", "min" or
    None (which value is bold in LaTeX and marked in Markdown); latex: header in LaTeX (default label);
    scale, unit: displayed value = stored value × scale, in ``unit`` (ASD: m → mm) — in every format;
    bounds: (low, high) of a valid stored value of a number column (None: any finite number). A value that is not
    a finite number inside them (a hand-edited ``Infinity`` or ``1e308`` GRecall) prints as ``invalid (...)``,
    with no interval, and is never the best."""

    key: str
    label: str
    digits: int | None = None
    better: str | None = None
    latex: str | None = None
    scale: float = 1.0
    unit: str = ""
    bounds: tuple[float, float] | None = None

    @property
    def csv_key(self) -> str:
        """The CSV header: the key, with its display unit when it has one (``asd_mm``)."""
        from spread.metrics.registry import unit_key

        return unit_key(self.key, self.unit)

    def display(self, value):
        """A stored number in the display unit (anything else as it is)."""
        if self.scale == 1.0 or isinstance(value, bool) or not isinstance(value, (int, float)):
            return value
        return float(value) * self.scale

    @property
    def arrow(self) -> str:
        return {"max": " ↑", "min": " ↓"}.get(self.better or "", "")

    def valid(self, value) -> float | None:
        """``value`` as a float when it is a finite number inside :attr:`bounds`, finite in display units too, else
        None."""
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return None
        try:
            number = float(value)  # an integer of 400 digits does not convert
        except OverflowError:
            return None
        if not math.isfinite(number) or not math.isfinite(number * self.scale):  # 1e307 m shown in mm is inf
            return None
        lo, hi = self.bounds if self.bounds is not None else (-math.inf, math.inf)
        return number if lo <= number <= hi else None

    def format(self, value) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "–"
        if self.digits is not None and self.valid(value) is not None:
            return f"{float(value) * self.scale:.{self.digits}f}"
        if self.digits is not None:  # text, ±inf or out of range (a hand-edited metrics.json): never a number
            return f"invalid ({str(value)[:20]!r})" if isinstance(value, str) else f"invalid ({value!r:.20})"
        return str(value)

    def half_width(self, record: dict) -> float | None:
        """Half the width of the record's interval for this column, None without one (or for an invalid value)."""
        lo, hi = record.get(f"{self.key}_lo"), record.get(f"{self.key}_hi")
        if self.digits is None or self.valid(record.get(self.key)) is None:
            return None
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (lo, hi)):
            return None
        if float(hi) < float(lo):  # an inverted interval (a hand edit): no interval, never a negative ±
            return None
        return (float(hi) - float(lo)) / 2 * self.scale

    def cell(self, record: dict, latex: bool = False) -> str:
        """The printed cell: the value, with ``± half-width`` when the record has an interval for it."""
        value = record.get(self.key)
        text = self.format(value)
        half = self.half_width(record)
        if half is None or text == "–" or self.valid(value) is None:
            return text
        if latex:
            return rf"{text}\,{{\scriptsize$\pm${half:.{self.digits}f}}}"
        return f"{text} ± {half:.{self.digits}f}"


def metric_column(spec) -> Column:
    """The column of a registered value (:class:`~spread.metrics.registry.ValueSpec`) or metric."""
    return Column(spec.name, spec.label, spec.digits, spec.better, spec.latex, spec.scale, spec.unit,
                  bounds=spec.valid_range)


def metric_columns(names=None, with_set: bool = True, hidden: bool = False) -> list[Column]:
    """The results tables' metric columns: the values of the selected registered metrics (None: the default four)
    in the paper's order, then FID and KID (KID is unbiased: it can be slightly below 0 when two sets match);
    ``hidden``: also the values not printed in tables (Stability's ``still_fraction``: CSV and wandb)."""
    from spread.metrics.registry import display_values

    return [metric_column(v) for v in display_values(names, with_set) if v.shown or hidden]


def columns_of(records: Sequence[dict], with_set: bool = True, hidden: bool = False) -> list[Column]:
    """The metric columns of every registered metric some record has a value for (default four at least)."""
    from spread.metrics.registry import METRICS, default_metric_names

    names = default_metric_names()
    names += [n for n in METRICS.names() if n not in names and any(r.get(n) is not None for r in records)]
    return metric_columns(names, with_set, hidden)


def set_columns() -> list[Column]:
    """The columns of the set-level statistics (FID, KID)."""
    from spread.metrics.registry import SET_METRICS

    return [metric_column(v) for v in SET_METRICS]


def value_column(key: str, columns: Sequence[Column] = ()) -> Column | None:
    """The column of ``key``: one of ``columns``, else a registered value's (so a unit is never lost), else None."""
    from spread.metrics.registry import value_spec

    for column in columns:
        if column.key == key:
            return column
    spec = value_spec(key)
    return None if spec is None else metric_column(spec)


def best_rows(records: Sequence[dict], column: Column) -> set[int]:
    """Indices of the rows holding the best value of ``column`` (ties all count; none without ``better``)."""
    values = [(i, column.valid(r.get(column.key))) for i, r in enumerate(records)]
    values = [(i, v) for i, v in values if v is not None]
    if column.better not in ("max", "min") or len(values) < 2:
        return set()
    best = (max if column.better == "max" else min)(v for _, v in values)
    return {i for i, v in values if v == best}


def markdown_cell(text) -> str:
    """``text`` as one Markdown table cell: ``|`` escaped, line breaks as spaces (a run folder named ``a|b``
    stays one cell)."""
    return " ".join(str(text).replace("\\", "\\\\").replace("|", "\\|").split())


def markdown_table(records: Sequence[dict], columns: Sequence[Column]) -> str:
    """A GitHub Markdown table; the best value of each ranked column is bold; every cell escaped
    (:func:`markdown_cell`)."""
    best = {c.key: best_rows(records, c) for c in columns}
    lines = ["| " + " | ".join(markdown_cell(c.label + c.arrow) for c in columns) + " |",
             "|" + "|".join("---" if c.digits is None else "---:" for c in columns) + "|"]
    for i, r in enumerate(records):
        cells = [markdown_cell(c.cell(r)) for c in columns]
        cells = [f"**{s}**" if i in best[c.key] else s for s, c in zip(cells, columns)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def latex_escape(text: str) -> str:
    """``text`` with LaTeX's special characters escaped."""
    text = text.replace("\\", "\x00")
    for char in "_%&#${}":
        text = text.replace(char, "\\" + char)
    return text.replace("\x00", r"\textbackslash{}")


def latex_table(records: Sequence[dict], columns: Sequence[Column], caption: str = "", label: str = "") -> str:
    """A booktabs ``table`` like the paper's ablation table; the best value per column is bold."""
    best = {c.key: best_rows(records, c) for c in columns}
    spec = "".join("l" if c.digits is None else "c" for c in columns)
    head = " & ".join(c.latex or latex_escape(c.label) for c in columns)
    rows = []
    for i, r in enumerate(records):
        cells = [c.cell(r, latex=True) if c.half_width(r) is not None and r.get(c.key) is not None
                 else latex_escape(c.format(r.get(c.key))).replace("–", "--") for c in columns]
        cells = [rf"\textbf{{{s}}}" if i in best[c.key] else s for s, c in zip(cells, columns)]
        rows.append("    " + " & ".join(cells) + r" \\")
    parts = [r"\begin{table}[t]", r"  \centering"]
    if caption:
        parts.append(rf"  \caption{{{caption}}}")
    parts += [rf"  \begin{{tabular}}{{{spec}}}", r"    \toprule", f"    {head} \\\\", r"    \midrule", *rows,
              r"    \bottomrule", r"  \end{tabular}"]
    if label:
        parts.append(rf"  \label{{{label}}}")
    parts.append(r"\end{table}")
    return "\n".join(parts) + "\n"


def display_rows(records: Sequence[dict], keys: Sequence[str],
                 columns: Sequence[Column] = ()) -> tuple[list[str], list[list]]:
    """(header, rows) of ``keys`` in display units: a key with a unit (a column's, else a registered value's) and
    its ``_lo`` / ``_hi`` bounds and ``_sd`` are headed ``<key>_<unit>`` (``asd_mm``, ``asd_mm_lo``) and scaled; the
    rest as they are. What CSV files and wandb tables hold."""
    from spread.metrics.registry import SCALED_SUFFIXES

    header, convert = [], []
    for key in keys:
        base = key[:-3] if key.endswith(SCALED_SUFFIXES) else key
        column = value_column(key, columns) or (value_column(base, columns) if base != key else None)
        if column is not None and column.unit:
            header.append(column.csv_key + key[len(base):] if base != key and column.key == base else column.csv_key)
            convert.append(column.display)
        else:
            header.append(key)
            convert.append(None)
    rows = [[r.get(k) if f is None else f(r.get(k)) for k, f in zip(keys, convert)] for r in records]
    return header, rows


def csv_text(records: Sequence[dict], keys: Sequence[str], columns: Sequence[Column] = ()) -> str:
    """CSV of ``keys`` in display units (:func:`display_rows`); floats by ``repr``, None as an empty cell."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    header, rows = display_rows(records, keys, columns)
    writer.writerow(header)
    for row in rows:
        writer.writerow(["" if v is None else (repr(v) if isinstance(v, float) else v) for v in row])
    return buf.getvalue()


def html_table(records: Sequence[dict], columns: Sequence[Column]) -> str:
    """An HTML ``<table>`` of ``columns`` (cells as in Markdown: display unit, ``± half-width``)."""
    import html

    head = "".join(f"<th>{html.escape(c.label + c.arrow)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c.cell(r))}</td>" for c in columns) + "</tr>" for r in records)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def parse_cell(text: str):
    """A CSV cell back to None, bool, int, float or str."""
    if text == "":
        return None
    if text in ("True", "False"):
        return text == "True"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def read_csv(path: str | Path) -> list[dict]:
    """Records of a CSV written by :func:`write_csv` (cells parsed by :func:`parse_cell`)."""
    from spread.io import read_text_checked

    text = read_text_checked(path)
    return [{k: parse_cell(v) for k, v in row.items()} for row in csv.DictReader(io.StringIO(text, newline=""))]


def write_csv(records: Sequence[dict], keys: Sequence[str], path: str | Path, columns: Sequence[Column] = ()) -> Path:
    write_text_atomic(path, csv_text(records, keys, columns))
    return Path(path)


def record_keys(records: Iterable[dict], first: Sequence[str] = ()) -> list[str]:
    """``first``, then every other key of the records in order of appearance."""
    keys = list(first)
    for r in records:
        keys += [k for k in r if k not in keys]
    return keys


#: Row fields that record how a row's intervals were drawn (:func:`spread.reporting.intervals.ci_columns`).
CI_SETTINGS = ("ci_level", "ci_resamples", "ci_seed", "ci_few")


def with_bounds(keys: Sequence[str], records: Sequence[dict]) -> list[str]:
    """``keys`` with ``<key>_lo``, ``<key>_hi`` right after each key whose bounds some record has, and the
    :data:`CI_SETTINGS` some record has at the end (so that a CSV always says which seed drew its bounds)."""
    present = {k for r in records for k in r} | set(keys)
    bounds = {f"{k}_{b}" for k in keys for b in ("lo", "hi")} & present
    out = []
    for key in keys:
        if key not in bounds:
            out += [key, *[b for b in (f"{key}_lo", f"{key}_hi") if b in bounds]]
    if bounds:
        out += [k for k in CI_SETTINGS if k in present and k not in out]
    return out


def write_tables(records: Sequence[dict], columns: Sequence[Column], stem: str | Path, caption: str = "",
                 label: str = "", csv_keys: Sequence[str] | None = None,
                 formats: Sequence[str] = ("md", "csv", "tex"), note: str = "", md_extra: str = "") -> dict[str, Path]:
    """``stem.md`` / ``stem.csv`` / ``stem.tex`` (atomic writes); CSV holds ``csv_keys`` (default: the columns'
    keys, then every other record key) in display units (:func:`display_rows`), each followed by its interval
    bounds where records have them;
    ``note`` goes under the Markdown table and at the end of the LaTeX caption, ``md_extra`` (Markdown: images,
    links) under the Markdown table only. Returns format → path."""
    stem = Path(stem)
    out = {}
    if "md" in formats:
        out["md"] = stem.with_suffix(".md")
        write_text_atomic(out["md"], (f"{caption}\n\n" if caption else "") + markdown_table(records, columns)
                          + "".join(f"\n{text}\n" for text in (note, md_extra) if text))
    if "csv" in formats:
        keys = list(csv_keys) if csv_keys is not None else record_keys(records, [c.key for c in columns])
        out["csv"] = write_csv(records, with_bounds(keys, records), stem.with_suffix(".csv"), columns)
    if "tex" in formats:
        out["tex"] = stem.with_suffix(".tex")
        full = " ".join(p for p in (caption, note) if p)
        write_text_atomic(out["tex"], latex_table(records, columns, latex_escape(full).replace("±", r"$\pm$"),
                                                  label))
    return out
