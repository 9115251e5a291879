"""Run records → the results DataFrame (:func:`frame`), and what its columns are: settings, metrics and their
display units (:func:`display`). Conventions: :mod:`spread.results.load`."""

from __future__ import annotations

import pandas as pd

#: Columns a row carries besides its settings and metrics, first in the frame.
FIRST = ("run", "source", "kind", "identity", "point", "seed", "status", "reused")


def frame(records: list[dict]) -> pd.DataFrame:
    """Records (each with a ``settings`` dict, as :mod:`spread.reporting.runs` makes them) as a DataFrame: each
    setting a column; ``attrs`` name the setting and metric columns."""
    settings: list[str] = []
    rows = []
    for r in records:
        flat = dict(r.get("settings") or {})
        settings += [k for k in flat if k not in settings]
        rows.append({**{k: v for k, v in r.items() if k != "settings"}, **flat})
    df = pd.DataFrame(rows)
    first = [c for c in FIRST if c in df.columns]
    df = df[[*first, *[c for c in settings if c not in first], *[c for c in df.columns
                                                                   if c not in first and c not in settings]]]
    df.attrs["settings"] = [c for c in settings if c in df.columns]
    df.attrs["metrics"] = metric_columns(df)
    return df


def metric_columns(df: pd.DataFrame) -> list[str]:
    """The registered values (and FID, KID) among ``df``'s columns, in the registry's order."""
    from spread.metrics.registry import METRICS, display_values

    return [v.name for v in display_values(METRICS.names()) if v.name in df.columns]


def unit_of(metric: str) -> tuple[str, float]:
    """(display unit, scale: display value = stored × scale) of a metric column (``("", 1.0)`` for a share or an
    unregistered column)."""
    from spread.metrics.registry import value_spec

    spec = value_spec(metric)
    return ("", 1.0) if spec is None else (spec.unit, float(spec.scale))


def display(df: pd.DataFrame) -> pd.DataFrame:
    """A copy of ``df`` with each metric, its bounds and its sd over seeds in its display unit, the column headed with the unit
    (``asd`` in metres → ``asd_mm`` in millimetres), as the platform's tables show them."""
    from spread.metrics.registry import SCALED_SUFFIXES, unit_key, value_spec

    out = df.copy()
    renamed = {}
    for metric in df.attrs.get("metrics") or metric_columns(df):
        spec = value_spec(metric)
        if spec is None or not spec.unit:
            continue
        for key in (metric, *(metric + suffix for suffix in SCALED_SUFFIXES)):
            if key in out.columns:
                out[key] = pd.to_numeric(out[key], errors="coerce") * float(spec.scale)
                renamed[key] = unit_key(metric, spec.unit) + key[len(metric):]
    out = out.rename(columns=renamed)
    out.attrs = {**df.attrs, "metrics": [renamed.get(m, m) for m in df.attrs.get("metrics", [])]}
    return out


#: Settings that may follow the seed: an evaluation seed set to the sampling seed (a sweep's ``seeds=K``).
SEED_FOLLOWERS = ("protocol.seed",)


def seed_columns(df: pd.DataFrame, seed: str = "seed") -> list[str]:
    """``seed`` and the settings that follow it (:data:`SEED_FOLLOWERS` equal to it in every row that has a seed):
    the seed, not settings (a mean over seeds pools them; a ranking of settings leaves them out)."""
    def same(a, b) -> bool:  # equal in every row that has a seed (a ground-truth evaluation has none)
        a, b = pd.to_numeric(a, errors="coerce"), pd.to_numeric(b, errors="coerce")
        return bool(b.notna().any() and ((a == b) | b.isna()).all())

    follows = [k for k in SEED_FOLLOWERS if k in df.columns and seed in df.columns and same(df[k], df[seed])]
    return [seed, *follows]


def swept_settings(df: pd.DataFrame, seed: str = "seed") -> list[str]:
    """The settings of ``df`` that take more than one value (:func:`levels`), the seed and those following it left
    out."""
    return [k for k in settings_of(df, exclude=tuple(seed_columns(df, seed))) if levels(df[k]) > 1]


def levels(column: pd.Series) -> int:
    """How many values a setting takes over the rows, missing (a row that lacks the setting: a ground-truth
    evaluation has no checkpoint, sampler or seed) counted as one of them."""
    return int(column.nunique(dropna=False))


def settings_of(df: pd.DataFrame, exclude=("seed",)) -> list[str]:
    """The setting columns of ``df`` (``attrs["settings"]``, else every column not a metric, bound or record
    field), less ``exclude``."""
    known = df.attrs.get("settings")
    if not known:
        metrics = set(df.attrs.get("metrics") or metric_columns(df))
        bounds = {f"{m}_{b}" for m in metrics for b in ("lo", "hi")}
        known = [c for c in df.columns if c not in metrics | bounds and c not in FIRST]
    return [c for c in known if c in df.columns and c not in exclude]
