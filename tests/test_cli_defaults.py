"""Every command that starts a process pool, run as a user runs it: the console script in a subprocess at
its default process count (the README's command lines), on tiny data.

``spread-sample`` (2 Ray actors) and ``spread-evaluate`` (a local Ray cluster) run through their console scripts
in tests/test_train_sample.py; this file covers the pool commands: import (both sources), generate, export.
A command schema must pickle by name in a fresh process (a spawn pool receives it).
"""

from __future__ import annotations

import json
import pickle
import subprocess
import sys

import pytest

import realdata
from helpers import compose, run_script
from spread.configs import to_object

FAST_IMPORT = ["decomposition=hull", "renders=0", "fidelity_samples=200"]  # processes stays at its default (2)


@pytest.mark.parametrize("command, overrides", [
    ("import", ["source=spread_release", "src=/s", "out_dir=/o"]),
    ("export", ["scenes=/s", "out_dir=/o"]),
    ("sample", ["ckpt=/c", "data.root=/d", "out_dir=/o"]),
    ("evaluate", ["scenes=/s", "reference=/r", "out_dir=/o"]),
])
def test_every_command_schema_pickles_by_name_into_a_fresh_process(command, overrides, tmp_path):
    record = to_object(compose(command, *overrides))
    path = tmp_path / "cfg.pkl"
    path.write_bytes(pickle.dumps(record))
    code = f"import pickle; r = pickle.load(open({str(path)!r}, 'rb')); print(type(r).__name__, r.out_dir)"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == [type(record).__name__, "/o"]


def test_spread_import_release_at_its_default_process_count(tmp_path):
    src = realdata.release_layout(tmp_path / "src")
    out = tmp_path / "out"
    assert to_object(compose("import", "source=spread_release", f"src={src}", f"out_dir={out}")).processes == 2
    proc = run_script("spread-import", "source=spread_release", f"src={src}", f"out_dir={out}", "progress=false",
                      *FAST_IMPORT)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["processes"] == 2
    assert manifest["failed_rooms"] == 0 and sum(manifest["counts"].values()) == 4, proc.stdout
    assert manifest["relations_agreement"]["spatial_agreement"] == 1.0


def test_spread_import_threed_front_at_its_default_process_count(tmp_path):
    src, splits = realdata.threed_front_layout(tmp_path / "threed_front_bedroom", tmp_path / "3D-FUTURE-model")
    out = tmp_path / "out"
    run_script("spread-import", "source=threed_front", f"src={src}", f"splits={splits}", "room_type=bedroom",
               f"future_models={tmp_path / '3D-FUTURE-model'}", f"out_dir={out}", "progress=false", *FAST_IMPORT)
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["config"]["processes"] == 2
    assert manifest["failed_rooms"] == 0 and sum(manifest["counts"].values()) == 4


def test_spread_generate_and_export_at_their_defaults(tmp_path):
    from spread.assets.build import build_library
    from spread.scene import list_scene_files

    build_library(tmp_path / "lib", categories=["dining_table", "chair", "mug"], variants=1, processes=1,
                  progress=False, caches=False)
    data = tmp_path / "rooms"
    run_script("spread-generate", f"out_dir={data}", "rooms=10", "progress=false", "renders=0",
               f"assets.copy_from={tmp_path / 'lib'}", "room.max_objects=4")
    manifest = json.loads((data / "manifest.json").read_text())
    assert manifest["config"]["processes"] == 2 and not manifest["failed_rooms"]
    test_files = list_scene_files(data / "test")
    assert test_files
    run_script("spread-export", f"scenes={data / 'test'}", f"out_dir={tmp_path / 'urdf'}", "progress=false")
    report = json.loads((tmp_path / "urdf" / "export.json").read_text())
    assert len(report["written"]) == len(test_files) and not report["failed"]


@pytest.mark.slow
def test_spread_import_at_all_its_defaults_as_the_readme_shows(tmp_path):
    """The README's line exactly (CoACD decomposition, renders, 2 processes): ~50 s on 2 cores."""
    src = realdata.release_layout(tmp_path / "src")
    out = tmp_path / "out"
    run_script("spread-import", "source=spread_release", f"src={src}", f"out_dir={out}")
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["failed_rooms"] == 0 and sum(manifest["counts"].values()) == 4
