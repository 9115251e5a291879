"""Shared test helpers (import as ``from helpers import ...``; pytest puts tests/ on sys.path).

* ``SMALL_MODEL``: the tiny model shrunk further (tests check plumbing, not learning).
* ``compose``: a Hydra config of ``conf/`` with overrides; ``run_script``: a console script in a subprocess
  (wandb disabled) that must succeed.
* ``asset_library``: the generated asset library (all or some categories) in a folder, its files copied from one
  build shared by the test session; ``make_dataset``: a small generated dataset (its own asset library), copied
  from one generation per session too;
  ``settled_room``: one generated, physics-settled kitchen of ≥ 8 objects and its small library (for physics and
  export tests); ``train_in_process`` / ``sample_in_process``: ``spread-train`` / ``spread-sample`` without a
  subprocess.
* ``scene_of``: a small hand-made :class:`spread.scene.Scene` from asset ids and poses (the one builder of the
  tests' scenes).
* ``load_script``: a script of ``benchmarks/`` imported as a module (its functions tested without a subprocess).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

from spread.configs import to_object

SMALL_MODEL = ["model.config.depth=1", "model.config.dim=32", "model.config.dim_head=8", "model.config.heads=2",
               "model.config.edge_dim=16", "model.config.index_dim=8", "model.config.num_latents=4",
               "model.config.shape_tokens=4", "model.config.shape_dim=16", "model.config.tokenizer_width=16",
               "model.config.tokenizer_points=32", "model.config.num_points=32", "model.config.cond_dim=32"]
QUIET = ["trainer.enable_progress_bar=false", "trainer.enable_model_summary=false"]
FAST_TRAIN = [*QUIET, "logger=csv", "trainer.num_sanity_val_steps=0", "data.batch_size=4"]
FAST_SAMPLE = ["sampler.steps=4", "progress=false", "renders=2", "figures=0", "batch_size=2", "workers=0"]
SCRIPTS = Path(sys.executable).parent
BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def compose(config_name: str, *overrides: str):
    from spread.configs import compose as compose_config

    return compose_config(config_name, list(overrides))


def load_script(name: str):
    """``benchmarks/<name>.py`` imported as a module named ``name`` (the folder is not put on sys.path)."""
    spec = importlib.util.spec_from_file_location(name, BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_script(name: str, *args: str, timeout: int = 600, ok: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "WANDB_MODE": "disabled", "HYDRA_FULL_ERROR": "1"}
    proc = subprocess.run([str(SCRIPTS / name), *args], env=env, capture_output=True, text=True, timeout=timeout)
    if ok:
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-5000:]
    return proc


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now (for a server a test starts and stops)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def user_error(name: str, *args: str, timeout: int = 300, cwd: Path | None = None) -> tuple[str, subprocess.CompletedProcess]:
    """A console script run as a user runs it (no HYDRA_FULL_ERROR, wandb disabled) that must be refused: the one
    stderr line it ends with (``<name>: ...``, no traceback), and the process."""
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "SPREAD_DEBUG")}
    proc = subprocess.run([str(SCRIPTS / name), *args], env={**env, "WANDB_MODE": "disabled"}, capture_output=True,
                          text=True, timeout=timeout, cwd=cwd)
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    assert lines and lines[-1].startswith(f"{name}: "), proc.stderr[-3000:]
    return lines[-1], proc


#: A folder shared by the test session's processes (tests/conftest.py sets it): builds that many tests repeat.
SESSION_CACHE = "SPREAD_TEST_CACHE"


def asset_library(root: Path, categories=None, seed: int = 0):
    """``build_library(root, categories, seed=seed)``: the same library, built once per test session (in one process:
    the suite keeps both cores busy, so a pool would only add its workers' start-up; test_assets checks that a pool
    builds the same library).

    The first call for these arguments builds it in the session's cache folder (under a file lock: the xdist
    workers share it); every call copies those files into ``root`` (byte for byte what a build there writes: the
    library's files hold no absolute path) and loads it, so a test may change its copy freely. Without a session
    cache it simply builds."""
    from filelock import FileLock

    from spread.assets import AssetLibrary
    from spread.assets.build import build_library

    cache = os.environ.get(SESSION_CACHE)
    if cache:
        key = hashlib.sha256(json.dumps([list(categories) if categories is not None else None, seed]).encode())
        shared = Path(cache) / f"assets-{key.hexdigest()[:16]}"
        shared.parent.mkdir(parents=True, exist_ok=True)
        with FileLock(f"{shared}.lock"):
            if not (shared / "index.json").exists():
                partial = shared.with_name(shared.name + ".partial")
                shutil.rmtree(partial, ignore_errors=True)
                build_library(partial, categories=categories, seed=seed, processes=1, progress=False)
                partial.rename(shared)
        shutil.copytree(shared, root, dirs_exist_ok=True)
        return AssetLibrary.load(root)
    return build_library(root, categories=categories, seed=seed, processes=1, progress=False)


def make_dataset(root: Path, rooms: int = 12, seed: int = 7, max_objects: int = 8, categories=None) -> Path:
    """``root/assets`` (the asset library) and ``root/data`` (rooms; 20% val, 30% test); returns ``root/data``.
    Generated once per test session for these arguments (as :func:`asset_library`: in the session's cache folder,
    under a file lock) and copied; the one absolute path in its files, the manifest's ``assets.copy_from``, is
    rewritten to ``root/assets``, so the copy is what a generation in ``root`` writes (but its timings)."""
    from filelock import FileLock

    lib = root / "assets"
    asset_library(lib, categories=categories)
    out = root / "data"
    cache = os.environ.get(SESSION_CACHE)
    if not cache:
        _generate(out, lib, rooms, seed, max_objects)
        return out
    args = [rooms, seed, max_objects, list(categories) if categories is not None else None]
    shared = Path(cache) / f"data-{hashlib.sha256(json.dumps(args).encode()).hexdigest()[:16]}"
    shared_lib = shared.with_name(shared.name + "-assets")
    with FileLock(f"{shared}.lock"):
        if not (shared / "manifest.json").exists():
            asset_library(shared_lib, categories=categories)
            partial = shared.with_name(shared.name + ".partial")
            shutil.rmtree(partial, ignore_errors=True)
            _generate(partial, shared_lib, rooms, seed, max_objects)
            partial.rename(shared)
    shutil.copytree(shared, out, dirs_exist_ok=True)
    manifest = out / "manifest.json"
    text = manifest.read_text()
    here, there = json.dumps(str(lib))[1:-1], json.dumps(str(shared_lib))[1:-1]
    assert text.count(there) == 1, f"{manifest}: expected the shared library's path once"
    manifest.write_text(text.replace(there, here))
    return out


def _generate(out: Path, lib: Path, rooms: int, seed: int, max_objects: int) -> None:
    from spread.procgen.dataset import AssetSource, DatasetConfig, generate_dataset
    from spread.procgen.room_types import RoomConfig

    generate_dataset(out, DatasetConfig(rooms=rooms, seed=seed, processes=1, renders=0, val_fraction=0.2,
                                        test_fraction=0.3, assets=AssetSource(copy_from=str(lib)),
                                        room=RoomConfig(max_objects=max_objects)), progress=False)


def settled_room(root: Path, min_objects: int = 8):
    """(Scene, AssetLibrary): the first kitchen of seeds 0, 1, ... with ≥ ``min_objects`` objects, generated and
    settled by :func:`spread.procgen.room.generate_room` from a 10-category, 1-variant library under ``root``."""
    import numpy as np

    from spread.assets.build import build_library
    from spread.procgen.room import generate_room
    from spread.procgen.room_types import RoomConfig
    from spread.procgen.settle import SettleConfig

    # no plates or bowls: nested ones sit millimetres apart, where the spatial code flips with sub-millimetre motion
    library = build_library(root / "assets", categories=["kitchen_counter", "shelf", "dining_table", "chair", "book",
                                                        "mug", "cup", "bottle", "jar", "box"],
                            variants=1, processes=1, progress=False, caches=False)
    for seed in range(20):
        result = generate_room(f"kitchen{seed}", np.random.default_rng(seed), library,
                               RoomConfig(room_types={"kitchen": 1.0}, max_objects=24), SettleConfig())
        if result.scene is not None and result.scene.num_objects >= min_objects:
            return result.scene, library
    raise AssertionError(f"no kitchen of {min_objects}+ objects in 20 seeds")


def train_in_process(out: Path, *overrides: str) -> dict:
    from spread.commands.train import train

    cfg = compose("train", f"out_dir={out}", *overrides)
    return train(cfg, run_dir=out, overrides=list(overrides))


def sample_in_process(*overrides: str):
    from spread.sampling import run_sampling

    return run_sampling(to_object(compose("sample", *FAST_SAMPLE, *overrides)))


def scene_of(asset_ids, translation, rotation=None, *, library=None, categories=None, spatial=None, physical=None,
             room=None, scene_id: str = "s", posed_codes: bool = False, extras=None):
    """A hand-made :class:`spread.scene.Scene` of N objects, in the conventions of DESIGN §3: metres, y-up, floor
    at y = 0; object i is placed by ``v_world = rotation[i] @ v_local + translation[i]``.

    ``asset_ids`` (N,) ids; ``translation`` (N, 3) metres, the world position of each asset's canonical bbox
    centre; ``rotation`` (N, 3, 3) world-from-local (None: identity, the asset's canonical orientation).
    ``categories`` (N,): None takes each asset's category from ``library`` when given, else the asset ids.
    ``spatial`` (N, N) codes: given ones are kept; else ``posed_codes=True`` computes them from the posed meshes
    of ``library`` (:func:`spread.relations.scene_spatial_codes`, on the float32 poses the scene stores), and
    otherwise every pair reads 0 "right of" (a placeholder) with 6 "self" on the diagonal. ``physical`` (N, N)
    codes, None: no relations. ``room`` (2, 3) min, max corners in metres or None; ``extras`` extra arrays.
    """
    import numpy as np

    from spread.relations import scene_spatial_codes
    from spread.scene import SPATIAL_SELF, Scene

    n = len(asset_ids)
    if rotation is None:
        rotation = np.tile(np.eye(3), (n, 1, 1))
    if categories is None:
        categories = [library[a].category for a in asset_ids] if library is not None else list(asset_ids)
    scene = Scene(scene_id, asset_ids, categories, translation, rotation,
                  np.zeros((n, n), np.int8) if spatial is None else spatial,
                  np.zeros((n, n), np.int8) if physical is None else physical, room=room, extras=dict(extras or {}))
    if spatial is None:
        if posed_codes:
            if library is None:
                raise ValueError("scene_of(posed_codes=True) needs the asset library the poses are read with")
            scene.spatial = scene_spatial_codes(scene.translation, scene.rotation, list(scene.asset_id), library)
        else:
            np.fill_diagonal(scene.spatial, SPATIAL_SELF)
    return scene
