"""Normalisation statistics of a dataset (``stats.json``) and the translation normalisation.

As in the reference (``Scale_Rot6d``): translations (world bbox centres, metres) are clipped to the
dataset bounds and mapped to [−1, 1] per axis, ``2·(t − min)/(max − min) − 1``; rotations (6D) are
not scaled. ``bounds_translations`` is ``[min x, min y, min z, max x, max y, max z]`` over every
object of the scenes given (the training split). An axis whose range is below
:data:`MIN_SPAN` (all objects at one height, say) is widened symmetrically to it, so the
normalisation never divides by zero.
"""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path
from typing import Iterable, Mapping

import numpy as np

from spread.io import read_json_object, write_json_atomic

STATS_VERSION = 1
#: Smallest range (metres) kept on a translation axis.
MIN_SPAN = 0.01


class StatsError(ValueError):
    """``stats.json`` is missing or malformed; the message names the file and the key."""


def compute_stats(scenes: Iterable) -> dict:
    """Statistics of Scene records: translation bounds, object-count histogram, category counts."""
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    counts: Counter = Counter()
    cats: Counter = Counter()
    n_scenes = 0
    for scene in scenes:
        t = np.asarray(scene.translation, np.float64)
        lo, hi = np.minimum(lo, t.min(0)), np.maximum(hi, t.max(0))
        counts[int(len(t))] += 1
        cats.update(str(c) for c in scene.category)
        n_scenes += 1
    if n_scenes == 0:
        raise ValueError("compute_stats: no scenes given")
    span = hi - lo
    pad = np.where(span < MIN_SPAN, (MIN_SPAN - span) / 2, 0.0)
    lo, hi = lo - pad, hi + pad
    return {
        "version": STATS_VERSION,
        "bounds_translations": [float(v) for v in lo] + [float(v) for v in hi],
        "num_scenes": n_scenes,
        "num_objects": int(sum(n * k for n, k in counts.items())),
        "max_objects": int(max(counts)),
        "object_count_histogram": {str(n): int(counts[n]) for n in sorted(counts)},
        "category_counts": {c: int(cats[c]) for c in sorted(cats)},
    }


def save_stats(path: str | os.PathLike, stats: Mapping) -> Path:
    """Validate and write ``stats`` as JSON, atomically."""
    path = Path(path)
    translation_bounds(stats, source=str(path))
    write_json_atomic(path, dict(stats))
    return path


def load_stats(path: str | os.PathLike) -> dict:
    """Read ``stats.json``; raise :class:`StatsError` naming the file and the bad key."""
    path = Path(path)
    if not path.exists():
        raise StatsError(f"{path}: stats file does not exist (compute it with spread.data.compute_stats)")
    stats = read_json_object(path, StatsError)
    translation_bounds(stats, source=str(path))
    return stats


def translation_bounds(stats: Mapping, source: str = "stats") -> tuple[np.ndarray, np.ndarray]:
    """(min (3,), max (3,)) float64 from ``stats['bounds_translations']``, validated."""
    key = "bounds_translations"
    if key not in stats:
        raise StatsError(f"{source}: key '{key}' is missing")
    try:
        b = np.asarray(stats[key], np.float64)
    except (TypeError, ValueError) as exc:
        raise StatsError(f"{source}: key '{key}' is not a list of numbers ({exc})") from None
    if b.shape != (6,) or not np.isfinite(b).all():
        raise StatsError(f"{source}: key '{key}' must be 6 finite numbers [min xyz, max xyz], got {stats[key]!r}")
    if (b[3:] <= b[:3]).any():
        raise StatsError(f"{source}: key '{key}' has max ≤ min on an axis: {b.tolist()}")
    return b[:3], b[3:]


def _bounds_like(t, stats):
    """(t as an array, min, max) with the bounds in t's float dtype and device."""
    if isinstance(stats, Mapping):
        lo, hi = translation_bounds(stats)
    else:
        b = np.asarray(stats, np.float64).reshape(6)
        lo, hi = b[:3], b[3:]
    if type(t).__module__.startswith("torch"):
        import torch

        if not t.is_floating_point():
            t = t.float()
        return t, torch.as_tensor(lo, dtype=t.dtype, device=t.device), torch.as_tensor(hi, dtype=t.dtype, device=t.device)
    t = np.asarray(t)
    dtype = np.result_type(t.dtype, np.float32)
    return t.astype(dtype, copy=False), lo.astype(dtype), hi.astype(dtype)


def normalize_translation(t, stats):
    """(..., 3) metres → [−1, 1] per axis (clipped to the bounds first); numpy or torch.

    ``stats`` is the stats dict or the 6 bounds ``[min xyz, max xyz]``. float32 stays float32.
    """
    t, lo, hi = _bounds_like(t, stats)
    if type(t).__module__.startswith("torch"):
        import torch

        t = torch.minimum(torch.maximum(t, lo), hi)
    else:
        t = np.clip(t, lo, hi)
    return 2 * (t - lo) / (hi - lo) - 1


def denormalize_translation(x, stats):
    """Inverse of :func:`normalize_translation` (no clipping): [−1, 1] → metres."""
    x, lo, hi = _bounds_like(x, stats)
    return (x + 1) / 2 * (hi - lo) + lo
