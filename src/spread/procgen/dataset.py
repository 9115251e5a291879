"""Write a dataset folder (DESIGN §4): ``assets/``, ``train/ val/ test/`` scene files, ``stats.json``,
``manifest.json`` and a few top-down renders.

Deterministic by seed: room ``k`` draws from ``np.random.default_rng([seed, k, attempt])`` and settles
in a fresh physics client, so its file does not depend on how many processes run or in which order.
Resumable: rooms whose file exists are not generated again; every file is written atomically. ``generation.json``
pins what the rooms are made with (:meth:`DatasetConfig.fingerprint`) before the first room is written; a re-run with
other settings (another seed, room or settle config, split fractions, assets) or asking fewer rooms than the folder
holds is refused by name before any work, so a folder never mixes two datasets and its manifest never describes rooms
made otherwise.
"""

from __future__ import annotations

import multiprocessing as mp
import math
import os
import time
from collections import Counter
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from spread import __version__
from spread.io import read_json, write_json_atomic
from spread.procgen.room import HullCache, generate_room
from spread.procgen.room_types import RoomConfig
from spread.procgen.settle import SettleConfig
from spread.runtime.ray import sigterm_exits
from spread.scene import PHYSICAL_SUPPORT, read_scene, write_scene

GENERATOR_VERSION = "spread-procgen-1"
SPLITS = ("train", "val", "test")


@dataclass
class AssetSource:
    """Where a dataset's asset library comes from. seed: the library's own seed (datasets with different
    room seeds share assets); variants: per category; categories: None for every category of the catalog;
    copy_from: an existing library folder to copy instead of building one (same assets for several datasets)."""

    seed: int = 0
    variants: int = 5
    categories: list[str] | None = None
    copy_from: str | None = None


@dataclass
class DatasetConfig:
    """``spread-generate``'s settings (``conf/generate.yaml`` overrides these defaults). rooms: how many;
    seed: the rooms' seed; processes: worker processes, at least 1 (never more than the rooms left to make nor
    than this machine's CPUs: :func:`pool_size`; the output does not depend on it); val_fraction /
    test_fraction: shares of val and test rooms, by room index (the rest is train); max_attempts: a room whose
    objects all fail settling is redrawn with the next sub-seed; renders: top-down PNGs of the first test rooms."""

    rooms: int = 200
    seed: int = 0
    processes: int = 2
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    max_attempts: int = 6
    renders: int = 8
    assets: AssetSource = field(default_factory=AssetSource)
    room: RoomConfig = field(default_factory=RoomConfig)
    settle: SettleConfig = field(default_factory=SettleConfig)

    def fingerprint(self) -> dict:
        """What the rooms' files depend on (:func:`fingerprint_of`): everything but how many rooms, processes and
        renders, and where the assets were copied from."""
        return fingerprint_of(asdict(self))


def split_of(index: int, config: DatasetConfig) -> str:
    """Deterministic split by index: in each block of 10 consecutive rooms, the last ones go to test then
    val (0.1/0.1: indices ending in 9 are test, in 8 val), so even a small dataset has every split."""
    period = 10
    k = index % period
    n_test = int(round(config.test_fraction * period))
    n_val = int(round(config.val_fraction * period))
    if k >= period - n_test:
        return "test"
    if k >= period - n_test - n_val:
        return "val"
    return "train"


def scene_id_of(index: int, seed: int) -> str:
    return f"s{seed}_{index:06d}"


# ---- worker side ---------------------------------------------------------------------------------

_WORKER: dict = {}


def _init_worker(assets_root: str) -> None:
    from spread.assets import AssetLibrary

    lib = AssetLibrary.load(assets_root)
    _WORKER["library"] = lib
    _WORKER["hulls"] = HullCache(lib)


def _make_room(args) -> dict:
    index, out_dir, config = args
    lib = _WORKER["library"]
    split = split_of(index, config)
    path = Path(out_dir) / split / f"{scene_id_of(index, config.seed)}.npz"
    started = time.perf_counter()
    removed: Counter = Counter()
    for attempt in range(config.max_attempts):
        rng = np.random.default_rng([config.seed, index, attempt])
        result = generate_room(scene_id_of(index, config.seed), rng, lib, config.room, config.settle,
                               hulls=_WORKER["hulls"])
        removed.update(result.report.removed)
        if result.scene is not None:
            result.scene.extras["generator"] = np.asarray(f"{GENERATOR_VERSION} seed={config.seed} "
                                                          f"index={index} attempt={attempt}")
            write_scene(result.scene, path)
            return {"index": index, "split": split, "ok": True, "attempts": attempt + 1,
                    "seconds": time.perf_counter() - started, "removed": dict(removed),
                    "placed": result.placed, "kept": result.scene.num_objects}
    return {"index": index, "split": split, "ok": False, "attempts": config.max_attempts,
            "seconds": time.perf_counter() - started, "removed": dict(removed)}


# ---- driver --------------------------------------------------------------------------------------

#: Settings a room file does not depend on: how many rooms (room k is the same in a dataset of any size), how
#: many processes make them, how many renders, where the asset library was copied from (its content is the index).
NOT_IN_FINGERPRINT = ("rooms", "processes", "renders")
PIN = "generation.json"


def fingerprint_of(config: dict) -> dict:
    """What a dataset's room files depend on, from a :class:`DatasetConfig` as a dict (a manifest's ``config``, with
    whatever else the command held: ``out_dir``, ``progress`` are left out), with the generator's version."""
    keep = {f.name for f in fields(DatasetConfig)} - set(NOT_IN_FINGERPRINT)
    out = {k: v for k, v in config.items() if k in keep}
    if isinstance(out.get("assets"), dict):
        out["assets"] = {k: v for k, v in out["assets"].items() if k != "copy_from"}
    return {"generator": GENERATOR_VERSION, **out}


def check_folder(out: Path, config: DatasetConfig) -> None:
    """Refuse, in one line naming what differs, a dataset folder whose rooms were made otherwise (module docstring):
    the fingerprint pinned in ``generation.json`` (or, for a folder made before that pin, its manifest's ``config``)
    against this run's (settings added after the record was written are not compared); more rooms than ``rooms``
    asks, or rooms this run would not make. A folder without rooms takes this run's settings (a run that failed
    before its first room); rooms without any record (a run of an earlier version stopped before its manifest) are
    continued when each is one this run would make, with a warning. Then pin this run's fingerprint
    (``status: running``)."""
    import logging

    from spread.runtime.fingerprint import described_changes, normalised

    now = normalised(config.fingerprint())
    present = sorted(p for s in SPLITS if (out / s).is_dir() for p in (out / s).glob("*.npz"))
    planned = {(split_of(i, config), f"{scene_id_of(i, config.seed)}.npz") for i in range(config.rooms)}
    extra = [p for p in present if (p.parent.name, p.name) not in planned]
    records = []  # every record there is: a pin damaged to fewer keys must not hide what the manifest says
    for path, key in ((out / PIN, "fingerprint"), (out / "manifest.json", "config")):
        if present and path.exists():
            try:
                record = read_json(path).get(key)
            except (OSError, ValueError, AttributeError):
                raise ValueError(f"{path}: not a readable record of the rooms' settings; generate into another "
                                 f"out_dir, or delete {out} to start over") from None
            if isinstance(record, dict) and not record:
                raise ValueError(f"{path}: key '{key}' records no setting; generate into another out_dir, or delete "
                                 f"{out} to start over")
            if isinstance(record, dict):
                records.append(record if key == "fingerprint" else normalised(fingerprint_of(record)))
    before = records[0] if records else None
    if present and before is None:
        if extra:
            raise ValueError(f"out_dir={out} holds {len(present)} room file(s) ({extra[0].name}, ...) without a "
                             f"record of the settings they were made with ({PIN}, manifest.json); generate into "
                             f"another out_dir")
        logging.getLogger("spread.generate").warning(
            "%s: %d room file(s) without a record of their settings (a run stopped before its manifest); continuing "
            "them as rooms of these settings (seed %d)", out, len(present), config.seed)
    if before is not None:
        changed = list(dict.fromkeys(c for record in records for c in described_changes(record, now, held_only=True)))
        if changed:
            shown = "; ".join(changed[:4])
            raise ValueError(f"out_dir={out} holds rooms generated with other settings (changed: {shown}"
                             f"{'; ...' if len(changed) > 4 else ''}); generate into another out_dir, or delete "
                             f"{out} to start over")
    if extra:
        raise ValueError(f"out_dir={out} holds {len(extra)} room(s) this run would not make ({extra[0].parent.name}/"
                         f"{extra[0].name}, ...; {len(present)} in all; rooms={config.rooms}); give rooms="
                         f"{len(present)} or more to keep and complete them, or generate into another out_dir")
    write_json_atomic(out / PIN, {"fingerprint": now, "status": "running"})


#: Whole-number settings of ``spread-generate`` and their least value (key as typed on the command line; the objects
#: of a room are whole here, their range is checked with each other).
WHOLE = {"seed": 0, "processes": 1, "max_attempts": 1, "assets.seed": 0, "assets.variants": 1,
         "room.min_objects": 0, "room.max_objects": 0, "room.max_stack": 1, "settle.max_steps": 1,
         "settle.verify_steps": 1, "settle.rounds": 1}
#: The most objects a room may be asked to hold (``room.max_objects``, and so ``room.min_objects``). The generator's
#: fullest rooms hold about 260: five rooms at ``room.object_density=1000 room.max_objects=1000`` kept 77–264
#: objects (24 s a room); a room asked for more fills its surfaces and then tries, attempt after attempt, to place
#: what cannot fit (``room.min_objects=400``: 116 s a room, then no room; ``=100000``: minutes a room, unbounded).
MAX_ROOM_OBJECTS = 512
#: Real-number settings: (least, most, whether the least is allowed).
REAL = {"room.object_density": (0.0, math.inf, True), "room.stack_probability": (0.0, 1.0, True),
        "room.on_object_probability": (0.0, 1.0, True), "room.wall_gap": (0.0, math.inf, True),
        "room.furniture_gap": (0.0, math.inf, True), "room.object_gap": (0.0, math.inf, True),
        "room.drop_height": (0.0, math.inf, True), "settle.rest_linear_speed": (0.0, math.inf, False),
        "settle.rest_angular_speed": (0.0, math.inf, False), "settle.max_slide": (0.0, math.inf, False),
        "settle.max_tilt": (0.0, math.inf, False), "settle.max_penetration": (0.0, math.inf, False),
        "settle.furniture_max_motion": (0.0, math.inf, False), "settle.verify_dt": (0.0, 1.0, False),
        "settle.verify_motion": (0.0, math.inf, False)}


def check_numbers(config: DatasetConfig) -> None:
    """``ValueError`` naming the key and value of a count that is not a whole number at least its least (:data:`WHOLE`:
    ``seed=-1``, ``max_attempts=0``, ``settle.rounds=0`` failed after the library was built, naming no key) or a
    measure that is not a finite number in its range (:data:`REAL`: ``room.object_density=nan`` failed inside numpy,
    ``settle.verify_dt=nan`` converting to an integer), or a room type's weight that is not a finite number ≥ 0
    (``room.room_types.kitchen=inf`` failed after the library was built with "Probabilities contain NaN", ``=nan``
    and ``=-1`` were taken as 0 and NaN written into generation.json and manifest.json)."""
    from spread.checks import whole_number

    def value(key: str):
        node = config
        for part in key.split("."):
            node = getattr(node, part)
        return node

    for key, least in WHOLE.items():
        whole_number(value(key), key, least)
    for key, (least, most, closed) in REAL.items():
        x = value(key)
        ok = isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x <= most and (
            x >= least if closed else x > least)
        if not ok:
            span = f"{'[' if closed else '('}{least:g}, {most:g}]" if math.isfinite(most) else \
                (f"≥ {least:g}" if closed else f"> {least:g}")
            raise ValueError(f"{key}={x!r}: expected a finite number {'in ' if math.isfinite(most) else ''}{span}")
    for name, weight in config.room.room_types.items():
        if not (isinstance(weight, (int, float)) and not isinstance(weight, bool) and math.isfinite(weight)
                and weight >= 0):
            raise ValueError(f"room.room_types.{name}={weight!r}: expected a finite number ≥ 0")


def check_config(config: DatasetConfig) -> list[str]:
    """Refuse settings that cannot make a dataset (before any work); return warnings for ones that make an
    unusual one (a split that gets no rooms), which the manifest records and the command prints."""
    if config.rooms < 1:
        raise ValueError(f"rooms={config.rooms}: a dataset needs at least 1 room")
    check_numbers(config)
    for key in ("val_fraction", "test_fraction"):
        value = getattr(config, key)
        if not 0.0 <= value <= 1.0:
            raise ValueError(f"{key}={value}: a fraction in [0, 1]")
    if config.val_fraction + config.test_fraction > 1.0:
        raise ValueError(f"val_fraction + test_fraction = {config.val_fraction + config.test_fraction} > 1")
    room = config.room
    if room.min_objects < 1 or room.max_objects < max(room.min_objects, 2):
        raise ValueError(f"room.min_objects={room.min_objects}, room.max_objects={room.max_objects}: a room holds "
                         f"between min_objects (≥ 1) and max_objects (≥ min_objects and ≥ 2) objects")
    if room.max_objects > MAX_ROOM_OBJECTS:
        raise ValueError(f"room.max_objects={room.max_objects}: at most {MAX_ROOM_OBJECTS} (the generator's fullest "
                         f"rooms hold about 260 objects; a room asked for more tries for minutes to place what "
                         f"cannot fit)")
    from spread.assets.catalog import CATALOG, default_categories
    from spread.procgen.room_types import ROOM_TYPES

    asked = config.assets.categories
    if asked is not None:  # else refused when the library was built, a KeyError traceback after the pin was written
        unknown = [c for c in asked if c not in CATALOG]
        if unknown or not asked:
            raise ValueError(f"assets.categories={list(asked)}: {'unknown ' + str(unknown) if unknown else 'none'} "
                             f"(known: {', '.join(default_categories())})")
    if not any(w > 0 and t in ROOM_TYPES for t, w in room.room_types.items()):
        raise ValueError(f"room.room_types={dict(room.room_types)}: no known room type with a positive weight "
                         f"(known: {sorted(ROOM_TYPES)})")
    counts = Counter(split_of(i, config) for i in range(config.rooms))
    warnings = []
    for split in ("train", "val", "test"):
        wanted = {"val": config.val_fraction, "test": config.test_fraction}.get(split, 1.0)
        if wanted > 0 and counts[split] == 0:
            warnings.append(f"rooms={config.rooms} gives the {split} split no rooms (rooms go to splits by index in "
                            f"blocks of 10: val_fraction={config.val_fraction}, test_fraction={config.test_fraction} "
                            f"need at least 10 rooms); spread-train needs val rooms, spread-sample test rooms")
    return warnings


def read_back(path: Path, library):
    """The room file's scene when it reads back as a valid scene of ``library``, else None (a relaunch makes the
    others again: a room is a function of its index and the seed)."""
    from spread.scene import read_scene

    try:
        return read_scene(path, library)
    except Exception:  # noqa: BLE001 - any reason it does not read back: made again
        return None


def check_places(out: Path, config: DatasetConfig) -> None:
    """``ValueError`` before anything is made when ``out`` holds another command's run (a training run's folder got
    a dataset beside its checkpoints, and could no longer be resumed) or lies inside ``assets.copy_from`` (the copy
    copied itself, level upon level, until Python's recursion limit)."""
    from spread.io import check_folder_kind

    check_folder_kind(out, "spread-generate", {"dataset"})
    if config.assets.copy_from and not (out / "assets" / "index.json").exists():  # a copy to make
        src, target = Path(config.assets.copy_from).resolve(), (out / "assets").resolve()
        if target == src or src in target.parents:
            raise ValueError(f"assets.copy_from={config.assets.copy_from}: out_dir={out} lies inside it, so the copy "
                             f"would hold itself; give an out_dir outside the library")


def pool_size(processes: int, jobs: int | None = None) -> int:
    """How many worker processes make ``jobs`` pieces of work (None: any number) when ``processes`` are asked: never
    more than the work (``rooms=7 processes=12`` with one room left to make started 12 workers for it), nor than this
    machine's CPUs."""
    return max(1, min(processes, os.cpu_count() or 1, processes if jobs is None else jobs))


def generate_dataset(out_dir: str | Path, config: DatasetConfig, progress: bool = True) -> dict:
    """Generate (or complete) the dataset folder; returns the manifest written. SIGTERM stops it and its workers
    (:func:`spread.runtime.ray.sigterm_exits`): the rooms written stay, a relaunch makes the others."""
    import logging

    out = Path(out_dir)
    check_places(out, config)
    warnings = check_config(config)
    for message in warnings:
        logging.getLogger("spread.generate").warning(message)
    with sigterm_exits():
        return _generate_dataset(out, config, progress)


def _generate_dataset(out: Path, config: DatasetConfig, progress: bool) -> dict:
    import logging

    from tqdm.auto import tqdm

    from spread.assets.build import build_library

    out.mkdir(parents=True, exist_ok=True)
    check_folder(out, config)
    t0 = time.perf_counter()
    if config.assets.copy_from and not (out / "assets" / "index.json").exists():
        import shutil

        src = Path(config.assets.copy_from)
        if not (src / "index.json").exists():
            raise FileNotFoundError(f"assets.copy_from={src}: no asset library there (missing index.json)")
        shutil.copytree(src, out / "assets", dirs_exist_ok=True)
    library = build_library(out / "assets", variants=config.assets.variants, seed=config.assets.seed,
                            categories=config.assets.categories, processes=pool_size(config.processes),
                            progress=progress)
    t_assets = time.perf_counter() - t0
    todo, damaged, kept = [], [], {}
    for index in range(config.rooms):
        path = out / split_of(index, config) / f"{scene_id_of(index, config.seed)}.npz"
        if path.exists():
            kept[path] = read_back(path, library)
            if kept[path] is None:  # cut short or damaged outside the platform's writes
                del kept[path]
                path.unlink()
                damaged.append(path.name)
        if not path.exists():
            todo.append((index, str(out), config))
    if damaged:
        logging.getLogger("spread.generate").warning(
            "%d room file(s) did not read back as valid scenes and are made again: %s", len(damaged),
            ", ".join(damaged[:3]) + (" …" if len(damaged) > 3 else ""))
    results = []
    t1 = time.perf_counter()
    if todo:
        workers = pool_size(config.processes, len(todo))
        if workers > 1:
            ctx = mp.get_context("spawn")
            with ctx.Pool(workers, initializer=_init_worker, initargs=(str(out / "assets"),)) as pool:
                for r in tqdm(pool.imap_unordered(_make_room, todo), total=len(todo), disable=not progress,
                              desc="rooms", unit="room"):
                    results.append(r)
        else:
            _init_worker(str(out / "assets"))
            for item in tqdm(todo, disable=not progress, desc="rooms", unit="room"):
                results.append(_make_room(item))
    t_rooms = time.perf_counter() - t1
    manifest = write_dataset_files(out, config, library, results, t_assets, t_rooms, read=kept)
    if config.renders > 0:
        write_renders(out, library, config.renders)
    return manifest


def dataset_statistics(scenes) -> dict:
    """Objects per room histogram, categories, support pairs per room, share of stacked objects."""
    counts = [s.num_objects for s in scenes]
    categories = Counter()
    support_pairs, stacked, small = [], 0, 0
    for s in scenes:
        categories.update(s.category.tolist())
        sup = s.physical == PHYSICAL_SUPPORT
        support_pairs.append(int(sup.sum()))
        supported = sup.any(axis=0)
        # stacked: supported by an object that is itself supported (not standing on the floor)
        supporter_of = {int(j): int(i) for i, j in np.argwhere(sup)}
        small += int(supported.sum())
        stacked += sum(1 for j, i in supporter_of.items() if i in supporter_of)
    hist = Counter(counts)
    return {
        "rooms": len(scenes),
        "objects": int(sum(counts)),
        "objects_per_room": {"min": int(min(counts, default=0)), "mean": float(np.mean(counts)) if counts else 0.0,
                             "max": int(max(counts, default=0)),
                             "histogram": {str(k): hist[k] for k in sorted(hist)}},
        "support_pairs_per_room": {"mean": float(np.mean(support_pairs)) if support_pairs else 0.0,
                                   "max": int(max(support_pairs, default=0))},
        "supported_objects": small,
        "share_stacked": float(stacked / small) if small else 0.0,
        "categories": dict(sorted(categories.items())),
    }


def write_dataset_files(out: Path, config: DatasetConfig, library, results: list[dict], t_assets: float,
                        t_rooms: float, read: dict | None = None) -> dict:
    """The statistics, manifest and dataset card of the rooms in ``out``; ``read``: room files already read back
    (path → scene; files not rewritten since), not read again."""
    from spread.data.stats import compute_stats, save_stats

    read = read or {}
    splits = {s: sorted((out / s).glob("*.npz")) if (out / s).exists() else [] for s in SPLITS}
    scenes = {s: [read[p] if p in read else read_scene(p, assets=library) for p in files]
              for s, files in splits.items()}
    train = scenes["train"] or [sc for v in scenes.values() for sc in v]
    removed = Counter()
    for r in results:
        removed.update(r.get("removed", {}))
    failed = [r["index"] for r in results if not r["ok"]]
    if not train:  # every room failed: say why, not "compute_stats: no scenes given"
        raise ValueError(f"no room was made: each of the {len(failed)} room(s) kept fewer than room.min_objects="
                         f"{config.room.min_objects} objects in max_attempts={config.max_attempts} attempts (objects "
                         f"removed in settling: {dict(removed) or 'none'}); lower room.min_objects or raise "
                         f"max_attempts")
    save_stats(out / "stats.json", compute_stats(train))
    all_scenes = [sc for v in scenes.values() for sc in v]
    from spread.runtime.fingerprint import normalised

    cfg = asdict(config)
    manifest = {
        "generator": GENERATOR_VERSION,
        "spread_version": __version__,
        "seed": config.seed,
        "config": cfg,
        "counts": {s: len(v) for s, v in scenes.items()},
        "failed_rooms": failed,
        "warnings": check_config(config),
        "categories": library.categories,
        "assets": len(library),
        "statistics": dataset_statistics(all_scenes),
        "this_run": {
            "rooms_generated": sum(1 for r in results if r["ok"]),
            "seconds_assets": round(t_assets, 2),
            "seconds_rooms": round(t_rooms, 2),
            "rooms_per_second": round(sum(1 for r in results if r["ok"]) / t_rooms, 3) if t_rooms > 0 and results else None,
            "mean_attempts": float(np.mean([r["attempts"] for r in results])) if results else None,
            "objects_removed_by_reason": dict(removed),
        },
    }
    write_json_atomic(out / "manifest.json", manifest)
    write_json_atomic(out / PIN, {"fingerprint": normalised(config.fingerprint()), "status": "done"})
    return manifest


def write_renders(out: Path, library, n: int) -> list[Path]:
    from spread.render import render_grid, render_topdown, save_png

    files = sorted((out / "test").glob("*.npz"))[:n] or sorted((out / "train").glob("*.npz"))[:n]
    images, paths = [], []
    for f in files:
        img = render_topdown(read_scene(f), library)
        p = out / "renders" / f"{f.stem}.png"
        save_png(img, p)
        images.append(img)
        paths.append(p)
    if images:
        save_png(render_grid(images, ncols=min(4, len(images))), out / "renders" / "overview.png")
    return paths


def load_manifest(root: str | Path) -> dict:
    path = Path(root) / "manifest.json"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no manifest (is {root} a dataset folder made by spread-generate?)")
    return read_json(path)
