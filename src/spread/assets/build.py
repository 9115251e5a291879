"""Build the procedural household library on disk: every category × variant, then the caches.

Deterministic: variant ``v`` of category ``c`` is drawn from ``variant_rng(seed, c, v)``, and the
mesh/parts files are byte-identical for the same seed, hence so are their content hashes.

Resumable: each finished asset leaves ``records/<asset_id>.json`` (its record and a fingerprint of
its spec). A rebuild regenerates the spec (cheap) and skips the expensive part — boolean union,
stability checks, export — when the fingerprint matches and the mesh and parts files still hash to
the recorded content hash. ``index.json`` is written atomically once, at the end.

Parallel: ``processes > 1`` fans the assets out over a spawn-context multiprocessing pool (safe on
every platform); the geometry caches are built afterwards by :meth:`AssetLibrary.build_caches`.
"""

from __future__ import annotations

import hashlib
import json
import multiprocessing as mp
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from spread.assets.assemble import AssetSpec, write_asset
from spread.assets.catalog import CATALOG, asset_id, default_categories, make_spec
from spread.assets.library import AssetLibrary, AssetRecord, reusable_record, write_record_sidecar

#: Bump when the builder's output for an unchanged spec changes (export, stability rules...).
BUILD_VERSION = 1


def spec_fingerprint(spec: AssetSpec) -> str:
    """sha256 of everything in a spec that determines the written asset (parts, poses, metadata)."""
    h = hashlib.sha256()
    meta = {
        "build_version": BUILD_VERSION, "asset_id": spec.asset_id, "category": spec.category,
        "variant": spec.variant, "role": spec.role, "density": spec.density, "tags": list(spec.tags),
        "rest_poses": {k: np.asarray(R, float).round(12).tolist() for k, R in spec.rest_poses.items()},
        "rest_weights": spec.rest_weights, "surfaces": [s.to_dict() for s in spec.support_surfaces],
    }
    h.update(json.dumps(meta, sort_keys=True).encode())
    for p in spec.parts:
        h.update(np.ascontiguousarray(p.vertices, np.float64).tobytes())
        h.update(np.ascontiguousarray(p.faces, np.int64).tobytes())
    return h.hexdigest()


def build_asset(root: str | Path, category: str, variant: int, seed: int) -> tuple[dict, bool]:
    """Build (or reuse) one asset; returns its record as a dict and whether it was (re)built."""
    root = Path(root)
    spec = make_spec(category, variant, seed)
    fingerprint = spec_fingerprint(spec)
    rec = reusable_record(root, spec.asset_id, fingerprint)
    if rec is not None:
        return rec.to_dict(), False
    rec = write_asset(root, spec)
    write_record_sidecar(root, spec.asset_id, fingerprint, rec)
    return rec.to_dict(), True


def _build_job(job: tuple[str, str, int, int]) -> tuple[dict, bool]:
    root, category, variant, seed = job
    try:
        return build_asset(root, category, variant, seed)
    except Exception as exc:  # name the asset: pool tracebacks lose the context
        raise RuntimeError(f"building asset '{asset_id(category, variant)}' (seed {seed}) failed: "
                           f"{type(exc).__name__}: {exc}") from exc


def build_library(root: str | Path, categories: Sequence[str] | None = None, variants: int = 5, seed: int = 0,
                  processes: int = 1, progress: bool = True, caches: bool = True) -> AssetLibrary:
    """Build ``variants`` variants of each category (default: all) under ``root``; return the library.

    Asset ids are ``<category>_<variant:02d>``. ``processes`` > 1 builds in parallel; ``progress``
    shows a tqdm bar; ``caches`` also builds the per-asset geometry caches.
    """
    from tqdm import tqdm

    root = Path(root)
    cats = default_categories() if categories is None else list(dict.fromkeys(categories))
    unknown = [c for c in cats if c not in CATALOG]
    if unknown:
        raise KeyError(f"unknown asset categories {unknown} (known: {', '.join(default_categories())})")
    if variants < 1:
        raise ValueError(f"variants must be at least 1, got {variants}")
    root.mkdir(parents=True, exist_ok=True)
    jobs = [(str(root), c, v, int(seed)) for c in cats for v in range(variants)]
    records: dict[str, AssetRecord] = {}
    bar = tqdm(total=len(jobs), desc="assets", unit="asset", disable=not progress)
    for rec_dict, _ in _run(jobs, processes):
        rec = AssetRecord.from_dict(rec_dict)
        records[rec.asset_id] = rec
        bar.update(1)
    bar.close()
    lib = AssetLibrary(root, records)
    lib.save_index(build={"seed": int(seed), "variants": int(variants), "categories": cats,
                          "build_version": BUILD_VERSION})
    if caches:
        lib.build_caches()
    return lib


def _run(jobs: list, processes: int) -> Iterable[tuple[dict, bool]]:
    """Results of ``_build_job`` over ``jobs``, serially or over a spawn pool."""
    if processes <= 1 or len(jobs) <= 1:
        yield from map(_build_job, jobs)
        return
    with mp.get_context("spawn").Pool(min(processes, len(jobs))) as pool:
        yield from pool.imap_unordered(_build_job, jobs, chunksize=max(1, len(jobs) // (8 * processes)))
