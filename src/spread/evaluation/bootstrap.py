"""Confidence intervals of the pooled metrics: a bootstrap over scenes (what ``metrics.json`` reports as
``<metric>_lo`` / ``<metric>_hi``, and every table prints as value ± half-width).

Every metric of DESIGN §6 is a **pooled ratio** over the evaluated scenes, each scene adding to a numerator
and a denominator (its torchmetrics states, ``per_scene.jsonl``'s ``state``): Col_mesh = colliding objects /
objects, GRecall = matching pairs / pairs, ASD = Σ|gap| / support pairs, Stability = unchanged (run, pair)s /
(run, pair)s, the still share = still (run, object)s / (run, object)s. A scene is the unit that is drawn
independently (its objects, pairs and physics runs are not independent of each other), so one bootstrap
resample draws n scenes with replacement from the n evaluated ones and recomputes each metric as the pooled
ratio of the drawn scenes' sums — not as a mean of per-scene ratios, which would weigh a 3-object room like a
30-object one and would not be the reported number.

The interval is the **percentile interval**: the (1 − level)/2 and (1 + level)/2 quantiles (numpy's default
linear interpolation) of the resampled ratios; resamples whose denominator is 0 (a metric no drawn scene
measured, e.g. ASD without support pairs) are left out. Resamples are ``numpy.random.default_rng(seed)
.integers(0, n, size=(resamples, n))``, drawn once and shared by every metric, so the same records and seed
give the same intervals, bit for bit. Defaults: 1,000 resamples, 95 %, the evaluation's seed.

FID and KID get no interval: they are statistics of the whole set against the reference set, not sums over
scenes (FID's bias changes with the number of distinct scenes, which a resample with repeats lowers), and each
resample would need a 2048 × 2048 matrix square root — minutes per table cell. KID's own subset estimate is
what ``metrics.json`` reports for it.
"""

from __future__ import annotations

import math
from typing import Iterable

import numpy as np

RESAMPLES = 1000
LEVEL = 0.95
#: Fewer scenes than this measuring a metric: its interval is flagged (a bootstrap over a handful of units is
#: too narrow).
FEW = 5


def scene_sums(records: Iterable[dict], metrics: dict) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """value → (numerators (n,), denominators (n,)) of the records usable for its metric (no ``error``, finite
    states, the metric did not fail on the scene: :func:`~spread.evaluation.aggregate.usable_for`), in order, for
    every pooled-ratio value of ``metrics`` (name → metric; each metric says which of its per-scene states form
    which value: :meth:`~spread.metrics.base.SceneMetric.pooled_terms`)."""
    from spread.evaluation.aggregate import usable_for

    records = list(records)
    out: dict[str, tuple[list, list]] = {}
    for name, metric in metrics.items():
        for value in metric.ratios:
            out[value] = ([], [])
        for r in records:
            if not usable_for(r, name, metrics):
                continue
            for value, (num, den) in metric.pooled_terms(r["state"][name]).items():
                out[value][0].append(num)
                out[value][1].append(den)
    return {k: (np.array(num, np.float64), np.array(den, np.float64)) for k, (num, den) in out.items()}


def pooled(num: np.ndarray, den: np.ndarray) -> float:
    """Σ num / Σ den, NaN when Σ den is 0."""
    with np.errstate(over="ignore"):  # an overflowing sum is inf: the caller asks for a finite value
        total, part = float(den.sum()), float(num.sum())
    return part / total if total > 0 else float("nan")


def resample_indices(n: int, resamples: int, seed: int) -> np.ndarray:
    """(resamples, n) scene indices drawn with replacement (module docstring)."""
    return np.random.default_rng(int(seed)).integers(0, n, size=(int(resamples), n))


def record_metrics(records: Iterable[dict]) -> dict:
    """name → a registered metric (default settings) for every metric whose states the records carry, in the
    records' order (the pooled-ratio definitions do not depend on the protocol's settings)."""
    from spread.metrics.registry import METRICS, default_metric_names, metric_spec

    names: list[str] = []
    for r in records:
        state, failed = r.get("state"), r.get("metric_errors")
        if not r.get("error") and isinstance(state, dict):
            measured = [*state, *(failed if isinstance(failed, dict) else ())]
            names += [n for n in measured if n not in names and n in METRICS]
    names = names or default_metric_names()  # nothing measured: the default metrics, each without an interval
    return {name: metric_spec(name).create() for name in names}


def bootstrap_intervals(records: Iterable[dict], resamples: int = RESAMPLES, level: float = LEVEL,
                        seed: int = 0, metrics: dict | None = None) -> dict:
    """``{"<value>_lo": ..., "<value>_hi": ..., "bootstrap": {...}}`` for every pooled-ratio value of ``metrics``
    (name → metric, e.g. ``protocol.build_metrics()``; default: the registered metrics whose states the records
    carry) over ``records`` (``per_scene.jsonl`` lines); None where a metric has no value or its resampled sums are
    not finite (finite states whose sums overflow: never written as NaN). ``bootstrap`` records the
    method, resamples, level, seed, the number of scenes and, per metric, how many of them measured it
    (``measured``: a non-zero denominator, e.g. ASD only counts rooms with support pairs — an interval
    resting on a handful of such rooms is too narrow to trust)."""
    if not 0 < level < 1:
        raise ValueError(f"level must be in (0, 1), got {level}")
    if resamples < 1:
        raise ValueError(f"resamples must be ≥ 1, got {resamples}")
    from spread.evaluation.aggregate import usable

    records = list(records)
    metrics = record_metrics(records) if metrics is None else metrics
    sums = scene_sums(records, metrics)
    n = sum(1 for r in records if usable(r, metrics))
    meta = {"method": "percentile", "unit": "scene", "resamples": int(resamples), "level": float(level),
            "seed": int(seed), "n_scenes": n, "measured": {m: int((den > 0).sum()) for m, (_, den) in sums.items()}}
    out: dict = {}
    indices: dict[int, np.ndarray] = {}  # one draw per scene count: every metric measured on all n scenes shares it
    quantiles = [(1 - level) / 2, (1 + level) / 2]
    for metric, (num, den) in sums.items():
        lo = hi = None
        m = len(num)  # scenes this metric was measured on (fewer than n where it failed on some)
        if m and math.isfinite(pooled(num, den)):  # sums that overflow (a hand-edited line's 1e308) give none
            if m not in indices:
                indices[m] = resample_indices(m, resamples, seed)
            index = indices[m]
            with np.errstate(over="ignore", invalid="ignore"):  # overflowing sums: no interval, below
                nb, db = num[index].sum(axis=1), den[index].sum(axis=1)
            ok = db > 0
            if ok.any():
                with np.errstate(over="ignore", invalid="ignore"):
                    lo, hi = (float(q) for q in np.quantile(nb[ok] / db[ok], quantiles))
                lo, hi = (lo, hi) if math.isfinite(lo) and math.isfinite(hi) else (None, None)
        out[f"{metric}_lo"], out[f"{metric}_hi"] = lo, hi
    out["bootstrap"] = meta
    return out


def few_measured(meta: dict | None) -> str:
    """``"asd (2), ..."``: the metrics fewer than :data:`FEW` (but some) scenes measured, "" when none."""
    counts = (meta or {}).get("measured") or {}
    return ", ".join(f"{m} ({k})" for m, k in counts.items() if 0 < k < FEW)


def interval_note(meta: dict | None) -> str:
    """One sentence saying what a table's ± is, from a ``bootstrap`` block (empty without one)."""
    if not meta:
        return ""
    note = (f"± is half the width of the {meta['level'] * 100:g} % {meta['method']} bootstrap interval over scenes "
            f"({meta['resamples']:,} resamples, seed {meta['seed']}); FID and KID have none.")
    few = few_measured(meta)
    if few:
        note += f" Fewer than {FEW} scenes measured {few}: too few for a trustworthy interval."
    return note
