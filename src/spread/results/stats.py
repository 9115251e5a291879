"""Questions asked of a results frame (:func:`spread.results.load`): intervals over seeds, "is this point
better?", which setting matters, the Pareto front.

* :func:`over_seeds` — per point (rows alike in every setting but ``seed``): the mean over its seeds and a 95 %
  Student-t interval (mean ± t₀.₉₇₅,ₙ₋₁ · s/√n; none with one seed), n seeds. The spread between seeds, where the
  per-run bootstrap intervals are the spread between scenes.
* :func:`paired_difference` — two points on the **same graphs and seeds**: per-scene values of ``per_scene.jsonl``
  matched by scene id (and by the run's sampling seed when several folders make a point), the mean of the paired
  differences A − B (each scene weighs the same) and a percentile bootstrap interval over the pairs (resamples
  drawn as :mod:`spread.evaluation.bootstrap` draws them, ``numpy.random.default_rng(seed)``).
* :func:`importance` — one-way η² per setting: the share of the metric's variance over the runs explained by that
  setting's levels alone (SS between / SS total); sorted, largest first. A quick ranking for a sweep, not an
  ANOVA over interactions.
* :func:`pareto` — the rows no other row beats in both of two metrics (default: Col_mesh down, GRecall up).

Values are in stored units (ASD in metres) as the frame holds them.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from spread.results.frame import levels, seed_columns, settings_of


def t_interval(values, level: float = 0.95) -> tuple[float, float, float, float]:
    """(mean, sample sd, lo, hi) of ``values`` (finite numbers): the Student-t interval mean ± t_{(1+level)/2, n-1}
    · sd/√n; NaN where it is undefined (no value; sd and bounds with one value)."""
    from scipy import stats

    x = np.asarray([float(v) for v in values if v is not None and math.isfinite(float(v))], dtype=float)
    n = len(x)
    mean = float(x.mean()) if n else math.nan
    sd = float(x.std(ddof=1)) if n > 1 else math.nan
    half = float(stats.t.ppf((1 + level) / 2, n - 1)) * sd / math.sqrt(n) if n > 1 else math.nan
    return mean, sd, mean - half, mean + half


def over_seeds(df: pd.DataFrame, metric: str, level: float = 0.95, seed: str = "seed") -> pd.DataFrame:
    """One row per point (module docstring): its settings, ``<metric>`` (the mean over seeds), ``<metric>_lo`` /
    ``<metric>_hi`` (the Student-t interval at ``level``; NaN with one seed), ``<metric>_sd``, ``n_seeds`` and
    ``seeds`` (the seeds, sorted). Rows of one run (the same ``point`` folder — or, in a store's frame, ``source``
    folder — seed and identity) count once; an evaluation
    seed that follows the sampling seed (``protocol.seed`` equal to ``seed`` in every row) is part of the seed, not a
    setting."""
    if metric not in df.columns:
        raise ValueError(f"over_seeds: no column {metric!r} (columns: {list(df.columns)})")
    attrs = dict(df.attrs)
    where = "point" if "point" in df.columns else "source" if "source" in df.columns else None
    if where is not None and seed in df.columns:  # one run read twice is one seed, not two: a point a search drew
        # twice, an MLflow store's runs of one folder (a relaunch that re-used or resumed it) with the same identity
        same = [where, seed, *(["identity"] if "identity" in df.columns else [])]
        named = df[where].notna()  # rows of no folder (a failed trial) are not one run
        df = pd.concat([df[named].drop_duplicates(subset=same, keep="last"), df[~named]]).sort_index()
        df.attrs = dict(attrs)
    # a setting some rows lack is a level of its own (a ground-truth evaluation has no checkpoint, sampler or seed:
    # it was pooled with a sampled run as a second seed)
    keys = [k for k in settings_of(df, exclude=tuple(seed_columns(df, seed))) if levels(df[k]) > 1]
    rows = []
    groups = df.groupby(keys, dropna=False, sort=True) if keys else [((), df)]
    for values, group in groups:
        values = values if isinstance(values, tuple) else (values,)
        x = pd.to_numeric(group[metric], errors="coerce").dropna().to_numpy(float)
        mean, sd, lo, hi = t_interval(x, level)
        seeds = sorted(group[seed].dropna().tolist()) if seed in group.columns else []
        rows.append({**dict(zip(keys, values)), metric: mean, f"{metric}_lo": lo, f"{metric}_hi": hi,
                     f"{metric}_sd": sd, "n_seeds": len(x), "seeds": seeds})
    out = pd.DataFrame(rows)
    out.attrs = {"settings": keys, "metrics": [metric], "level": level}
    return out


def scene_values(folders, metric: str) -> dict[tuple, float]:
    """(seed, scene id) → the scene's ``metric`` from the ``per_scene.jsonl`` of each folder (a run folder, or a
    list of them: one per seed); lines with an error or no finite value are left out."""
    from spread.reporting.intervals import folder_records
    from spread.reporting.runs import folder_identity, optional_json
    from spread.runtime.fingerprint import settings

    folders = [folders] if isinstance(folders, (str, Path)) else list(folders)
    out = {}
    for folder in folders:
        records = folder_records(folder)
        if records is None:
            raise ValueError(f"paired_difference: {folder}: no per_scene.jsonl")
        seed = settings(folder_identity(Path(folder), optional_json(Path(folder) / "metrics.json"))).get("seed") \
            if len(folders) > 1 else None
        for r in records:
            value = r.get(metric)
            if r.get("error") or not isinstance(value, (int, float)) or not math.isfinite(value):
                continue
            out[(r.get("seed", seed), str(r["scene_id"]))] = float(value)
    return out


def paired_difference(folder_a, folder_b, metric: str, resamples: int = 1000, seed: int = 0,
                      level: float = 0.95) -> dict:
    """``{"metric", "diff", "lo", "hi", "n_pairs", "a", "b", "level", "resamples", "seed"}``: the mean over
    matched scenes of A − B (``a``, ``b``: each side's mean over the same scenes) with its percentile bootstrap
    interval (module docstring). ``folder_a`` / ``folder_b``: a run folder or a list of them (one per seed).
    ``ValueError`` when the two share no scene (different graphs, or seeds), or one has no value of ``metric``."""
    if resamples < 1 or not 0 < level < 1:
        raise ValueError(f"paired_difference: resamples ≥ 1 and 0 < level < 1, got {resamples}, {level}")
    a, b = scene_values(folder_a, metric), scene_values(folder_b, metric)
    for folder, values in ((folder_a, a), (folder_b, b)):
        if not values:
            raise ValueError(f"paired_difference: {folder}: no scene with a per-scene {metric} value")
    shared = sorted(set(a) & set(b))
    if not shared:
        raise ValueError(f"paired_difference: {folder_a} and {folder_b} share no scene with a {metric} value "
                         f"(matched by scene id and seed: {len(a)} and {len(b)} scenes) — compare points sampled "
                         f"on the same graphs with the same seeds")
    da = np.array([a[k] for k in shared])
    db = np.array([b[k] for k in shared])
    d = da - db
    index = np.random.default_rng(int(seed)).integers(0, len(d), size=(int(resamples), len(d)))
    lo, hi = (float(q) for q in np.quantile(d[index].mean(axis=1), [(1 - level) / 2, (1 + level) / 2]))
    return {"metric": metric, "diff": float(d.mean()), "lo": lo, "hi": hi, "n_pairs": len(d),
            "a": float(da.mean()), "b": float(db.mean()), "level": level, "resamples": int(resamples),
            "seed": int(seed)}


def importance(df: pd.DataFrame, metric: str, settings: list[str] | None = None) -> pd.DataFrame:
    """Per setting that takes more than one value (``settings``: those to rank; default every setting but
    the seed and those following it, :func:`~spread.results.frame.seed_columns`): ``eta_squared`` (module docstring), ``levels`` (its distinct values), ``n`` (rows with a
    value of ``metric``); sorted by ``eta_squared``, largest first."""
    if metric not in df.columns:
        raise ValueError(f"importance: no column {metric!r}")
    data = df.assign(**{metric: pd.to_numeric(df[metric], errors="coerce")}).dropna(subset=[metric])
    y = data[metric].to_numpy(float)
    total = float(((y - y.mean()) ** 2).sum()) if len(y) else 0.0
    rows = []
    for key in settings if settings is not None else settings_of(df, exclude=tuple(seed_columns(df))):
        column = data[key].astype(str)  # a setting's levels (a list or a missing value is a level too)
        levels = column.nunique()
        if levels < 2:
            continue
        groups = data.groupby(column)[metric]
        between = float((groups.count() * (groups.mean() - y.mean()) ** 2).sum())
        rows.append({"setting": key, "eta_squared": between / total if total > 0 else 0.0, "levels": levels,
                     "n": len(y)})
    out = pd.DataFrame(rows, columns=["setting", "eta_squared", "levels", "n"])
    return out.sort_values("eta_squared", ascending=False, kind="stable").reset_index(drop=True)


def pareto(df: pd.DataFrame, x: str = "col_mesh", y: str = "grecall", minimize_x: bool = True,
           maximize_y: bool = True) -> pd.DataFrame:
    """The rows of ``df`` on the Pareto front of ``x`` and ``y`` (no other row is at least as good in both and
    better in one), sorted by ``x``; rows missing either value are left out."""
    for key in (x, y):
        if key not in df.columns:
            raise ValueError(f"pareto: no column {key!r}")
    data = df.assign(**{x: pd.to_numeric(df[x], errors="coerce"), y: pd.to_numeric(df[y], errors="coerce")})
    data = data.dropna(subset=[x, y])
    gx = -data[x].to_numpy(float) if minimize_x else data[x].to_numpy(float)  # larger is better, both
    gy = data[y].to_numpy(float) if maximize_y else -data[y].to_numpy(float)
    keep = [not np.any((gx >= gx[i]) & (gy >= gy[i]) & ((gx > gx[i]) | (gy > gy[i]))) for i in range(len(data))]
    return data[keep].sort_values(x, ascending=minimize_x, kind="stable")
