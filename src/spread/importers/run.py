"""``spread-import``: a source layout → the platform's dataset folder (DESIGN §4), in parallel, resumable.

Phases, all in one spawn-context process pool (``processes``; rooms and assets are independent):

1. **rooms**: the source's room list and splits (:meth:`~spread.importers.base.Source.rooms`);
2. **scan**: each room's file is read and checked, giving the assets it needs;
3. **assets**: every asset some readable room needs is imported into ``out_dir/assets`` (mesh cleaned,
   convex decomposition, record; :mod:`spread.assets.imported`), then the library index is written and
   the geometry caches built;
4. **relations** (sources whose files carry spatial codes): each room's codes are compared with the
   platform's codes of its posed meshes under every reading (:mod:`spread.importers.conventions`); the
   dataset's sums choose the reading (``relations.convention``), said on the console and in the manifest;
5. **scenes**: each room whose assets all imported becomes ``out_dir/<split>/<scene_id>.npz`` (the file's
   own graph; the platform's relations are computed from the posed meshes and compared with it).

Resumable: an asset whose inputs and files are unchanged is not imported again (its sidecar record), a
room whose scene file exists and whose line in ``out_dir/import/rooms.jsonl`` says it succeeded with the
same inputs (:func:`room_fingerprint`: its folder's files, its assets' content, the options) is not
converted again, and rooms and assets that failed are tried again. A room that fails loses the scene
file an earlier run wrote for it. Every file is written atomically, and
only under ``out_dir`` (scene ids and asset ids are :func:`spread.io.safe_name`s).

Failures never stop the import: each is recorded (tag, file, key, message) and counted in
``manifest.json``. ``stats.json`` holds the translation bounds of the source's ``dataset_stats.txt``
when it has them (``stats=source``, the authors' normalisation) or of the train split (``stats=computed``).
"""

from __future__ import annotations

import multiprocessing as mp
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import MISSING

from spread import __version__
from spread.importers.base import SPLITS, AssetRequest, RoomRef, error_record
from spread.importers.conventions import RelationsOptions
from spread.io import append_jsonl, check_input_file, read_jsonl, write_json_atomic

IMPORTER_VERSION = "spread-import-1"
SOURCES = ("spread_release", "threed_front")  # the built-in importers (every one: spread.importers.registry)


@dataclass
class ImportConfig:
    """Options of one import (``conf/import.yaml`` documents each): ``source`` (spread_release |
    threed_front), ``src`` (the source folder) and ``out_dir`` (the dataset folder written) are required."""

    source: str = MISSING
    src: str = MISSING
    out_dir: str = MISSING
    splits: str | None = None
    room_type: str | None = None
    future_models: str | None = None
    val_fraction: float = 0.05
    processes: int = 2
    progress: bool = True
    stats: str = "source"
    renders: int = 4
    decomposition: str = "coacd"
    decomposition_settings: dict = field(default_factory=dict)
    density: float = 400.0
    fidelity_samples: int = 2000
    relations: RelationsOptions = field(default_factory=RelationsOptions)

    def check(self) -> None:
        """``ValueError`` naming the option an import could not run with, before the source is read or the folder
        touched (a misspelled ``decomposition`` failed every asset, and the re-import then deleted every scene)."""
        import math

        if self.stats not in ("source", "computed"):
            raise ValueError(f"stats={self.stats!r}: expected 'source' or 'computed'")
        if not (isinstance(self.val_fraction, (int, float)) and math.isfinite(self.val_fraction)
                and 0 <= self.val_fraction < 1):
            raise ValueError(f"val_fraction={self.val_fraction!r}: a number in [0, 1) (the share of train rooms "
                             f"that become val where the source has no val split)")
        self.settings().check()
        self.relations.check()

    def settings(self):
        from spread.assets.imported import ImportSettings

        return ImportSettings(self.decomposition, dict(self.decomposition_settings), float(self.density),
                              int(self.fidelity_samples))


def make_source(cfg: ImportConfig):
    """The :class:`~spread.importers.base.Source` named by ``cfg.source`` (the importer registry,
    :mod:`spread.importers.registry`: ``spread_release``, ``threed_front`` and plugins)."""
    from spread.importers.registry import IMPORTERS

    if cfg.source not in IMPORTERS:
        raise ValueError(f"source={cfg.source!r}: expected one of {', '.join(IMPORTERS.names())}")
    return IMPORTERS.get(cfg.source)(cfg)


# ---- worker side ---------------------------------------------------------------------------------

_WORKER: dict = {}


def _init_worker(cfg: ImportConfig) -> None:
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _WORKER.clear()
    _WORKER["cfg"] = cfg
    _WORKER["source"] = make_source(cfg)


def _library():
    if "library" not in _WORKER:
        from spread.assets import AssetLibrary

        _WORKER["library"] = AssetLibrary.load(Path(_WORKER["cfg"].out_dir) / "assets")
    return _WORKER["library"]


def folder_hash(folder: str | Path) -> str:
    """SHA-256 over the names and bytes of the files directly in a room folder (its inputs; renders and
    other subfolders are not read by the importers)."""
    import hashlib

    h = hashlib.sha256()
    folder = Path(folder)
    if folder.is_dir():
        for path in sorted(p for p in folder.iterdir() if p.is_file()):
            h.update(path.name.encode() + b"\0")
            with open(check_input_file(path, max_bytes=0), "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 20), b""):
                    h.update(chunk)
    return h.hexdigest()


def room_fingerprint(scan: dict, records: dict, source_info: dict) -> str:
    """What a room's scene file depends on: its folder's files, its assets' content, the importer and options."""
    import hashlib
    import json

    return hashlib.sha256(json.dumps({
        "version": IMPORTER_VERSION, "folder": scan["folder_hash"], "source": source_info,
        "assets": [records[r.asset_id].content_hash for r in scan["requests"]],
    }, sort_keys=True, default=str).encode()).hexdigest()


def _scan_job(ref: RoomRef) -> dict:
    try:
        return {"tag": ref.tag, "requests": _WORKER["source"].scan(ref), "error": None,
                "folder_hash": folder_hash(ref.folder)}
    except Exception as exc:  # recorded, the import goes on
        return {"tag": ref.tag, "requests": None, "error": error_record(ref.tag, exc, ref.folder)}


def _asset_job(request: AssetRequest) -> dict:
    started = time.perf_counter()
    cfg = _WORKER["cfg"]
    try:
        record, built = _WORKER["source"].import_asset(Path(cfg.out_dir) / "assets", request, cfg.settings())
        from spread.assets.library import check_measures
        from spread.scene import check_asset_extents

        check_asset_extents(request.asset_id, record.extents, str(request.path))  # before any room uses it
        check_measures(record.to_dict())  # what a library refuses on load (a flat mesh's mass 0) fails this asset alone
        return {"asset_id": request.asset_id, "record": record.to_dict(), "built": built,
                "seconds": time.perf_counter() - started, "error": None}
    except Exception as exc:
        return {"asset_id": request.asset_id, "record": None, "built": False,
                "seconds": time.perf_counter() - started,
                "error": {**error_record(None, exc, request.path), "asset_id": request.asset_id}}


def agreement(scene, library) -> dict:
    """Counts comparing the scene's graph (the file's) with the platform's relations of its posed meshes."""
    from spread.relations import physical_codes, scene_spatial_codes
    from spread.scene import PHYSICAL_SUPPORT

    ids = [str(a) for a in scene.asset_id]
    n = scene.num_objects
    off = ~np.eye(n, dtype=bool)
    spatial = scene_spatial_codes(scene.translation, scene.rotation, ids, library)
    physical = physical_codes(scene.translation, scene.rotation, ids, library).codes
    file_sup, our_sup = scene.physical == PHYSICAL_SUPPORT, physical == PHYSICAL_SUPPORT
    return {"spatial_pairs": int(off.sum()), "spatial_equal": int(((spatial == scene.spatial) & off).sum()),
            "physical_equal": int(((physical == scene.physical) & off).sum()),
            "file_support": int(file_sup.sum()), "file_support_found": int((file_sup & our_sup).sum()),
            "platform_support": int(our_sup.sum())}


def _readings_job(args: tuple[RoomRef, list[AssetRequest]]) -> dict:
    """Agreement counts of one room's file spatial codes under every reading (module docstring, phase 4)."""
    from spread.importers.conventions import reading_counts
    from spread.relations import scene_spatial_codes

    ref, requests = args
    try:
        scene, _ = _WORKER["source"].scene(ref, _library(), requests)
        platform = scene_spatial_codes(scene.translation, scene.rotation, [str(a) for a in scene.asset_id], _library())
        return {"tag": ref.tag, "counts": reading_counts(scene.spatial, platform), "error": None}
    except Exception as exc:  # the room fails again, and is recorded, when it is written
        return {"tag": ref.tag, "counts": None, "error": error_record(ref.tag, exc, ref.folder)}


def _room_job(args: tuple[RoomRef, list[AssetRequest], str, str]) -> dict:
    from spread.importers.conventions import read_as
    from spread.scene import write_scene

    ref, requests, fingerprint, reading = args
    cfg = _WORKER["cfg"]
    started = time.perf_counter()
    try:
        library = _library()
        scene, counts = _WORKER["source"].scene(ref, library, requests)
        if getattr(_WORKER["source"], "spatial_from_file", False):
            scene.spatial = read_as(scene.spatial, reading).astype(np.int8)
        scene.validate(source=f"room '{ref.tag}' ({ref.folder})", assets=library)
        path = Path(cfg.out_dir) / ref.split / f"{ref.scene_id}.npz"
        write_scene(scene, path)
        return {"tag": ref.tag, "scene_id": ref.scene_id, "split": ref.split, "ok": True, "fingerprint": fingerprint,
                "objects": scene.num_objects,
                "room_type": str(scene.extras["room_type"]) if "room_type" in scene.extras else None,
                "agreement": agreement(scene, library), "counts": counts,
                "seconds": time.perf_counter() - started, "error": None}
    except Exception as exc:
        return {"tag": ref.tag, "scene_id": ref.scene_id, "split": ref.split, "ok": False,
                "seconds": time.perf_counter() - started, "error": error_record(ref.tag, exc, ref.folder)}


# ---- driver --------------------------------------------------------------------------------------

def build_caches_or_drop(library, requests: dict[str, AssetRequest], build: dict):
    """(the library without the assets whose geometry cache cannot be built, their error records): a
    degenerate mesh (Qhull fails on its hull) takes only its rooms with it, not the import. The index is
    written again when an asset was dropped."""
    from spread.assets import AssetLibrary

    failed = {}
    for aid in sorted(library.records):
        try:
            library.geometry(aid)
        except Exception as exc:  # recorded, the import goes on
            request = requests.get(aid)
            failed[aid] = {**error_record(None, exc, request.path if request else None), "asset_id": aid}
    if failed:
        library = AssetLibrary(library.root, {k: v for k, v in library.records.items() if k not in failed})
        library.save_index(build=build)
    return library, failed


def remove_stale_scenes(out: Path, history: list[dict], keep: set[Path]) -> list[str]:
    """Delete the scene files an earlier import wrote (lines of ``rooms.jsonl``) that this import does not
    have: a room that left the split file, or moved to another split (its old file), so the disk, the
    manifest and the splits agree and no room is in two splits. Only files named in the log are touched;
    returns them, relative to ``out``."""
    removed = []
    for line in history:
        split, scene_id = line.get("split"), line.get("scene_id")
        if split not in SPLITS or not isinstance(scene_id, str):
            continue
        path = out / split / f"{scene_id}.npz"
        if path not in keep and path.name == f"{scene_id}.npz" and path.parent == out / split and path.is_file():
            path.unlink()
            removed.append(f"{split}/{path.name}")
    return sorted(set(removed))


def split_warnings(counts: dict[str, int]) -> list[str]:
    """One warning per split left without scenes (a carved-out val room that failed, a test list whose rooms
    all failed): the dataset still imports, the manifest and the console say it."""
    return [f"the {split} split has no scenes after this import" + (" (spread-train validates on val: give it "
            "rooms or set trainer.limit_val_batches=0)" if split == "val" else "")
            for split in SPLITS if counts.get(split, 0) == 0]

def _map(pool, fn, items, desc: str, progress: bool):
    from tqdm.auto import tqdm

    if not items:
        return []
    it = pool.imap_unordered(fn, items) if pool is not None else map(fn, items)
    return list(tqdm(it, total=len(items), desc=desc, unit=desc.split()[0], disable=not progress))


def import_dataset(cfg: ImportConfig) -> dict:
    """Run the import (module docstring); returns the manifest written to ``out_dir/manifest.json``. The
    import holds ``out_dir``'s lock (:func:`spread.io.run_lock`) once the source has been checked."""
    from spread.io import run_lock

    cfg.check()
    check_not_another_kind(Path(cfg.out_dir))
    source = make_source(cfg)  # fails early (missing split file, bad options) before anything is written
    if cfg.stats == "source":
        from spread.importers.spread_release import read_dataset_stats

        read_dataset_stats(Path(cfg.src) / "dataset_stats.txt")  # bad bounds named now, not after every room
    room_list = source.rooms()
    with run_lock(cfg.out_dir, "spread-import"):
        return _import_dataset(cfg, source, room_list)


def check_not_another_kind(out: Path) -> None:
    """``ValueError`` when ``out`` holds a dataset an import did not make (``spread-generate``'s rooms: its
    ``generation.json``, or a ``manifest.json`` of another generator): an import would replace its asset index,
    statistics and manifest and leave its rooms pointing at assets the index no longer has. Also when ``out`` holds
    another command's run, or lies inside a dataset or a training run (:func:`spread.io.check_folder_kind`)."""
    from spread.io import check_folder_kind, read_json

    check_folder_kind(out, "spread-import", {"dataset"})  # another command's run, or inside a dataset or a run
    try:
        manifest = read_json(out / "manifest.json") if (out / "manifest.json").is_file() else {}
    except (OSError, ValueError):
        manifest = {}
    maker = manifest.get("generator") if isinstance(manifest, dict) else None
    if (out / "generation.json").exists() or (isinstance(maker, str) and not maker.startswith("spread-import")):
        raise ValueError(f"out_dir={out}: holds a dataset made by {maker or 'spread-generate'} (not an import); an "
                         f"import would replace its assets, statistics and manifest — import into another out_dir")


def first_failure(room_list, scans: dict, failed_assets: dict) -> dict:
    """The first room's failure (``{"tag", "file", "error"}``), else the first failed asset's, tagged "an asset"
    (an asset's record has no room tag: the message read "None: ...")."""
    room = next((scans[r.tag]["error"] for r in room_list.rooms if scans[r.tag]["error"]), None)
    if room:
        return room
    asset = next(iter(failed_assets.values()), {})
    return {**asset, "tag": asset.get("tag") or "an asset"}


def check_some_room_imported(room_list, failed: set[str], first: dict | None, earlier: int, out: Path,
                             src: str, index_written: bool = False) -> None:
    """``ValueError`` when this import makes no room at all — every listed room failed (``failed``: their tags;
    ``first``: the first failure), or the source lists none — while earlier imports' scenes are there: what failed
    (a source folder not mounted, a broken mesh tool) is said, and those scenes kept, not deleted as rooms that no
    longer import. Checked before the library's index is written (it is kept too) and again once the rooms are
    (``index_written``)."""
    if not earlier or (room_list.rooms and len(failed) < len(room_list.rooms)):
        return
    if room_list.rooms:
        first = first or {}
        what = (f"every one of the {len(room_list.rooms)} rooms failed (first: {first.get('tag')}: "
                f"{first.get('file')}: {first.get('error')})")
    else:
        what = (f"the source lists no room (src={src}: not mounted, or emptied?"
                + (f"; {room_list.errors[0]}" if room_list.errors else "") + ")")
    kept = "are kept" if index_written else "and their asset library are kept"
    raise ValueError(f"{what}; the {earlier} scene file(s) of earlier imports in {out} {kept} — see "
                     f"{out / 'import' / 'rooms.jsonl'}")


def settle_asset_requests(rooms: list[RoomRef], scans: dict[str, dict]) -> dict[str, AssetRequest]:
    """The one request each asset id is built from (``scans``: tag → a room's scan, its ``requests``). Rooms asking
    one id with other inputs (a category or size a mislabelled row gives another room's model) are outvoted: the
    inputs most rooms ask for win (the first room's on a tie) and each room asking otherwise fails, named, its scan
    replaced by the error — the odd room out, never the rooms that agree (the first room in order won before)."""
    asked: dict[str, dict[AssetRequest, list[str]]] = {}  # asset id → its requests → the rooms asking, in order
    for ref in rooms:
        for req in scans[ref.tag]["requests"] or []:
            tags = asked.setdefault(req.asset_id, {}).setdefault(req, [])
            if ref.tag not in tags:
                tags.append(ref.tag)
    folders = {ref.tag: ref.folder for ref in rooms}
    wanted: dict[str, AssetRequest] = {}
    for asset_id, variants in asked.items():
        best, agree = max(variants.items(), key=lambda item: len(item[1]))  # the first of the most-asked on a tie
        wanted[asset_id] = best
        for req, tags in variants.items():
            if req == best:
                continue
            differs = [f for f in ("category", "kind", "path", "size") if getattr(req, f) != getattr(best, f)]
            for tag in tags:
                if scans[tag]["requests"] is None:
                    continue  # failed already (another asset outvoted it)
                scans[tag] = {"tag": tag, "requests": None, "error": {
                    "tag": tag, "file": folders[tag], "key": None,
                    "error": f"asset id '{asset_id}' is asked for with other inputs ({', '.join(differs)}: "
                             f"{', '.join(repr(getattr(req, f)) for f in differs)}) than by {len(agree)} other "
                             f"room{'s' if len(agree) > 1 else ''} ({agree[0]}: "
                             f"{', '.join(repr(getattr(best, f)) for f in differs)}); a mislabelled object?"}}
    return wanted


def _import_dataset(cfg: ImportConfig, source, room_list) -> dict:
    from spread.assets import AssetLibrary, AssetRecord

    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "import" / "rooms.jsonl"
    from spread.io import refuse_links

    refuse_links(log_path, out / "manifest.json", out / "stats.json")  # before any work: see spread.io
    history = read_jsonl(log_path)
    done = {r["tag"]: r for r in history if r.get("ok")}
    earlier = sum(1 for split in SPLITS for _ in (out / split).glob("*.npz"))
    t0 = time.perf_counter()
    processes = max(1, int(cfg.processes))
    pool = mp.get_context("spawn").Pool(processes, initializer=_init_worker, initargs=(cfg,)) if processes > 1 else None
    if pool is None:
        _init_worker(cfg)
    try:
        scans = {r["tag"]: r for r in _map(pool, _scan_job, room_list.rooms, "rooms scanned", cfg.progress)}
        t_scan = time.perf_counter() - t0
        wanted = settle_asset_requests(room_list.rooms, scans)
        t1 = time.perf_counter()
        asset_results = _map(pool, _asset_job, sorted(wanted.values(), key=lambda r: r.asset_id),
                             "assets imported", cfg.progress)
        t_assets = time.perf_counter() - t1
        records = {r["asset_id"]: AssetRecord.from_dict(r["record"]) for r in asset_results if r["record"]}
        failed_assets = {r["asset_id"]: r["error"] for r in asset_results if r["error"]}
        unusable = {ref.tag for ref in room_list.rooms if scans[ref.tag]["error"]
                    or any(req.asset_id in failed_assets for req in scans[ref.tag]["requests"])}
        first = first_failure(room_list, scans, failed_assets)
        check_some_room_imported(room_list, unusable, first, earlier, out, cfg.src)  # before the index is replaced
        library = AssetLibrary(out / "assets", records)
        library.save_index(build={"importer": IMPORTER_VERSION, **source.info()})
        t2 = time.perf_counter()
        library, cache_failed = build_caches_or_drop(library, wanted, {"importer": IMPORTER_VERSION, **source.info()})
        failed_assets.update(cache_failed)
        records = dict(library.records)
        t_caches = time.perf_counter() - t2
        room_errors = list(room_list.errors)
        failed_refs: list[RoomRef] = []
        jobs = []
        info = source.info()
        usable = [ref for ref in room_list.rooms if not scans[ref.tag]["error"]
                  and not any(req.asset_id in failed_assets for req in scans[ref.tag]["requests"])]
        conventions = measure_conventions(pool, source, cfg, usable, scans)
        info = {**info, "spatial_reading": conventions["reading"]}
        for ref in room_list.rooms:
            scan = scans[ref.tag]
            if scan["error"]:
                room_errors.append(scan["error"])
                failed_refs.append(ref)
                continue
            missing = [req.asset_id for req in scan["requests"] if req.asset_id in failed_assets]
            if missing:
                first = failed_assets[missing[0]]
                room_errors.append({"tag": ref.tag, "file": first["file"], "key": first["key"],
                                    "error": f"asset '{missing[0]}' failed to import: {first['error']}"
                                             + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")})
                failed_refs.append(ref)
                continue
            fingerprint = room_fingerprint(scan, records, info)
            path = out / ref.split / f"{ref.scene_id}.npz"
            if done.get(ref.tag, {}).get("fingerprint") == fingerprint and path.exists():
                continue
            jobs.append((ref, scan["requests"], fingerprint, conventions["reading"]))
        t3 = time.perf_counter()
        results = _map(pool, _room_job, jobs, "rooms written", cfg.progress)
        t_rooms = time.perf_counter() - t3
    finally:
        if pool is not None:
            pool.close()
            pool.join()
    by_tag = {ref.tag: ref for ref in room_list.rooms}
    for r in results:
        append_jsonl(log_path, r)
        if r["ok"]:
            done[r["tag"]] = r
        else:
            room_errors.append(r["error"])
            failed_refs.append(by_tag[r["tag"]])
    check_some_room_imported(room_list, {ref.tag for ref in failed_refs}, room_errors[0] if room_errors else None,
                             earlier, out, cfg.src, index_written=True)
    for ref in failed_refs:  # a file left by an earlier run of a room that fails now is not data any more
        done.pop(ref.tag, None)
        (out / ref.split / f"{ref.scene_id}.npz").unlink(missing_ok=True)
    current = {ref.tag: ref for ref in room_list.rooms}
    done = {t: r for t, r in done.items() if t in current and r.get("split") == current[t].split}
    keep = {out / current[t].split / f"{current[t].scene_id}.npz" for t in done}
    removed = remove_stale_scenes(out, history, keep)
    manifest = write_manifest(out, cfg, source, room_list, library, done, room_errors, failed_assets, asset_results,
                              {"relations_convention": conventions,
                               "seconds_scan": t_scan, "seconds_assets": t_assets, "seconds_caches": t_caches,
                               "seconds_rooms": t_rooms, "rooms_written": sum(1 for r in results if r["ok"]),
                               "assets_built": sum(1 for r in asset_results if r["built"]),
                               "removed_stale": removed})
    if cfg.renders > 0:
        from spread.procgen.dataset import write_renders

        write_renders(out, library, cfg.renders)
    return manifest


def measure_conventions(pool, source, cfg: ImportConfig, rooms: list[RoomRef], scans: dict) -> dict:
    """Phase 4 (module docstring): the reading of the files' spatial codes, printed; raises
    :class:`~spread.importers.conventions.ConventionError` (nothing written for the rooms) when none agrees."""
    from spread.importers.conventions import add_counts, choose_reading

    if not getattr(source, "spatial_from_file", False):
        return {"reading": "as_stored", "chosen_by": "the platform computes every spatial code (one rule per graph)",
                "agreement": None, "pairs": 0, "ties": [], "message": None}
    results = _map(pool, _readings_job, [(ref, scans[ref.tag]["requests"]) for ref in rooms],
                   "relations measured", cfg.progress)
    totals: dict = {}
    for r in results:
        add_counts(totals, r["counts"])
    chosen = choose_reading(totals, cfg.relations)
    print(chosen["message"], flush=True)
    return chosen


def _sum(rows, key) -> int:
    return int(sum(r.get(key, 0) for r in rows))


def write_manifest(out: Path, cfg: ImportConfig, source, room_list, library, done: dict, room_errors: list,
                   failed_assets: dict, asset_results: list, run: dict) -> dict:
    """stats.json and manifest.json of the imported folder (module docstring)."""
    from spread.data.stats import compute_stats, save_stats
    from spread.importers.spread_release import read_dataset_stats
    from spread.procgen.dataset import dataset_statistics
    from spread.scene import read_scene

    current = {r.tag: r for r in room_list.rooms}
    good = {t: r for t, r in done.items() if t in current and (out / r["split"] / f"{r['scene_id']}.npz").exists()}
    files = {s: sorted(out / s / f"{r['scene_id']}.npz" for r in good.values() if r["split"] == s) for s in SPLITS}
    scenes = {s: [read_scene(p, assets=library) for p in fs] for s, fs in files.items()}
    all_scenes = [sc for v in scenes.values() for sc in v]
    stats = None
    if all_scenes:
        stats = compute_stats(scenes["train"] or all_scenes)
        source_stats = read_dataset_stats(Path(cfg.src) / "dataset_stats.txt")
        bounds = (source_stats or {}).get("bounds_translations")
        stats["bounds_source"] = "computed from the train split"
        if cfg.stats == "source" and isinstance(bounds, list) and len(bounds) == 6:
            stats["bounds_translations"] = [float(v) for v in bounds]
            stats["bounds_source"] = f"{Path(cfg.src) / 'dataset_stats.txt'} (bounds_translations)"
        save_stats(out / "stats.json", stats)
    agreements = [r["agreement"] for r in good.values()]
    agree = {k: _sum(agreements, k) for k in ("spatial_pairs", "spatial_equal", "physical_equal", "file_support",
                                               "file_support_found", "platform_support")}
    agree["spatial_agreement"] = agree["spatial_equal"] / agree["spatial_pairs"] if agree["spatial_pairs"] else None
    agree["physical_agreement"] = agree["physical_equal"] / agree["spatial_pairs"] if agree["spatial_pairs"] else None
    agree["file_support_recall"] = (agree["file_support_found"] / agree["file_support"]
                                    if agree["file_support"] else None)
    counts = Counter()
    for r in good.values():
        for k, v in (r.get("counts") or {}).items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                counts[k] += v
    fidelity = [r["record"]["source"]["decomposition"].get("fidelity", {}).get("hausdorff")
                for r in asset_results if r["record"] and "decomposition" in r["record"].get("source", {})]
    fidelity = [f for f in fidelity if f is not None]
    records = list(library.records.values())
    run = dict(run)
    conventions = run.pop("relations_convention", None)
    n_rooms = run["rooms_written"]
    manifest = {
        "generator": IMPORTER_VERSION,
        "spread_version": __version__,
        "source": source.info(),
        "config": asdict(cfg),
        "splits": room_list.splits,
        "counts": {s: len(v) for s, v in scenes.items()},
        "room_types": dict(Counter(str(sc.extras["room_type"]) for sc in all_scenes if "room_type" in sc.extras)),
        "warnings": split_warnings({s: len(v) for s, v in scenes.items()}),
        "failed_rooms": len(room_errors),
        "failed_assets": len(failed_assets),
        "errors": {"rooms": room_errors, "assets": list(failed_assets.values())},
        "categories": library.categories,
        "unknown_asset_categories": sorted({f"{a} -> {c}" for sc in all_scenes if "category_known" in sc.extras
                                            for a, c, k in zip(sc.asset_id, sc.category, sc.extras["category_known"])
                                            if not bool(k)}),
        "assets": len(library),
        "meshes": {"closed": sum(1 for r in records if r.source.get("closed")),
                   "open": sum(1 for r in records if r.source and not r.source.get("closed")),
                   "boxes": sum(1 for r in records if "box" in r.tags)},
        "decomposition": {"method": cfg.decomposition, "settings": dict(cfg.decomposition_settings),
                          "hausdorff_m": {"median": float(np.median(fidelity)), "max": float(np.max(fidelity))}
                          if fidelity else None},
        "relations_agreement": agree,
        "relations_convention": conventions,
        "relations_rule": getattr(source, "relations_rule", None),
        "room_counts": dict(counts),
        "statistics": dataset_statistics(all_scenes) if all_scenes else None,
        "stats_bounds": stats["bounds_source"] if stats else None,
        "this_run": {
            **{k: (round(v, 2) if isinstance(v, float) else v) for k, v in run.items()},
            "assets_per_second": round(run["assets_built"] / run["seconds_assets"], 3)
            if run["assets_built"] and run["seconds_assets"] > 0 else None,
            "rooms_per_second": round(n_rooms / run["seconds_rooms"], 3)
            if n_rooms and run["seconds_rooms"] > 0 else None,
        },
    }
    write_json_atomic(out / "manifest.json", manifest)
    return manifest
