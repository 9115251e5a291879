"""Round 17's review of ``spread-generate``: how many processes, the room types' weights, SIGTERM.

* ``processes=0`` and ``processes=-1`` were taken silently, and ``rooms=7 processes=12`` with one room left to make
  started 13 processes: a process count below one is refused by key before any work, and no more workers start than
  rooms are left to make, nor than the machine has CPUs.
* ``room.room_types.kitchen=inf`` failed after the asset library was built ("Probabilities contain NaN", no key);
  ``=nan`` and ``=-1`` were taken as 0 and NaN written into generation.json and manifest.json: refused by key.
* SIGTERM to the command left its pool's workers running on their own (re-parented to PID 1; they finished their
  room, then printed BrokenPipeError tracebacks and a leaked-semaphore warning): now the command and its workers end,
  with status 143, and a relaunch completes the dataset.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from helpers import SCRIPTS, asset_library, user_error

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def library(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("lib") / "assets"
    asset_library(root)
    return root


@pytest.mark.parametrize("processes", ["0", "-1"])
def test_spread_generate_refuses_a_process_count_below_one_by_key_before_any_work(tmp_path, processes):
    out = tmp_path / "data"
    out.mkdir()
    (out / "keep.txt").write_text("a file of the user's")
    line, _ = user_error("spread-generate", f"out_dir={out}", "rooms=2", f"processes={processes}", "renders=0",
                         "progress=false")
    assert line == (f"spread-generate: processes={processes}: expected a whole number ≥ 1 "
                    f"(HYDRA_FULL_ERROR=1 shows the traceback)"), line
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]  # no assets, no rooms, no log, no lock


def test_spread_generate_starts_no_more_workers_than_rooms_left_to_make_nor_than_cpus(tmp_path, library,
                                                                                      monkeypatch):
    """``rooms=7 processes=12`` with one room left to make started 12 workers (13 processes); the asset build was
    asked for 12 too. Now: one room left is made in the command's own process, three rooms take three workers, and
    neither the rooms nor the assets take more workers than the machine has CPUs."""
    import spread.assets.build as build_module
    import spread.procgen.dataset as dataset_module
    from spread.assets import AssetLibrary
    from spread.procgen.dataset import AssetSource, DatasetConfig, generate_dataset
    from spread.procgen.room_types import RoomConfig

    def config(rooms: int, processes: int) -> DatasetConfig:
        return DatasetConfig(rooms=rooms, seed=0, processes=processes, renders=0,
                             assets=AssetSource(copy_from=str(library)), room=RoomConfig(max_objects=8))

    made = tmp_path / "relaunched"
    generate_dataset(made, config(2, 1), progress=False)  # two rooms made; a relaunch asking three has one left

    class Stop(Exception):
        pass

    pools, inline, asset_processes = [], [], []

    def pool(n, **kwargs):
        pools.append(n)
        raise Stop

    def init_worker(root):
        inline.append(root)
        raise Stop

    def build_library(root, **kwargs):
        asset_processes.append(kwargs["processes"])
        return AssetLibrary.load(root)

    monkeypatch.setattr(dataset_module, "mp", SimpleNamespace(get_context=lambda kind: SimpleNamespace(Pool=pool)))
    monkeypatch.setattr(dataset_module, "_init_worker", init_worker)
    monkeypatch.setattr(build_module, "build_library", build_library)
    monkeypatch.setattr(os, "cpu_count", lambda: 64)

    with pytest.raises(Stop):
        generate_dataset(made, config(3, 12), progress=False)
    assert pools == [] and len(inline) == 1  # the one room left: no pool at all
    assert asset_processes == [12]
    with pytest.raises(Stop):
        generate_dataset(tmp_path / "three", config(3, 12), progress=False)
    assert pools == [3]
    monkeypatch.setattr(os, "cpu_count", lambda: 2)
    with pytest.raises(Stop):
        generate_dataset(tmp_path / "two-cpus", config(3, 12), progress=False)
    assert pools == [3, 2] and asset_processes == [12, 12, 2]


@pytest.mark.parametrize("weight, shown", [("inf", "inf"), ("nan", "nan"), ("-1", "-1.0")])
def test_spread_generate_refuses_a_room_type_weight_that_is_not_a_finite_number_of_at_least_zero_by_key_before_any_work(
        tmp_path, weight, shown):
    out = tmp_path / "data"
    line, _ = user_error("spread-generate", f"out_dir={out}", "rooms=2", f"room.room_types.kitchen={weight}",
                         "renders=0", "progress=false")
    assert line == (f"spread-generate: room.room_types.kitchen={shown}: expected a finite number ≥ 0 "
                    f"(HYDRA_FULL_ERROR=1 shows the traceback)"), line
    assert not out.exists()  # nothing made: no asset library, no generation.json holding NaN


def test_the_generate_config_says_how_to_ask_for_bedrooms_only():
    """``'room.room_types={bedroom:1.0}'`` merges into the defaults (Hydra's dict merge), so every type is still made;
    conf/generate.yaml's comment shows the line that asks for bedrooms only, and that line does."""
    from spread.configs import compose, to_object

    lines = (ROOT / "conf" / "generate.yaml").read_text().splitlines()
    said = next(i for i, text in enumerate(lines) if "Bedrooms only" in text)
    shown = " ".join(line.lstrip("# ").rstrip("\\") for line in lines[said + 1:said + 3])
    example = re.sub(r"^spread-generate \.\.\. ", "", shown).split()
    command = to_object(compose("generate", ["out_dir=/tmp/unused", *example]))
    assert {t for t, w in command.room.room_types.items() if w > 0} == {"bedroom"}


def _descendants(pid: int) -> list:
    import psutil

    try:
        return psutil.Process(pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return []


def _alive(process) -> bool:
    import psutil

    try:
        return process.is_running() and process.status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


def _is_resource_tracker(process) -> bool:
    import psutil

    try:
        return "resource_tracker" in " ".join(process.cmdline())
    except psutil.Error:
        return False


@pytest.mark.timeout(300)
def test_sigterm_ends_spread_generate_and_its_worker_processes_and_a_relaunch_completes_the_dataset(tmp_path,
                                                                                                   library):
    pytest.importorskip("psutil")
    out = tmp_path / "data"
    args = [str(SCRIPTS / "spread-generate"), f"out_dir={out}", "rooms=4", "seed=0", "processes=2", "renders=0",
            "progress=false", "room.max_objects=8", f"assets.copy_from={library}"]
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "SPREAD_DEBUG")}
    env.update(WANDB_MODE="disabled", OMP_NUM_THREADS="1")
    seen: dict[int, object] = {}
    log = tmp_path / "stderr.txt"
    with open(log, "w") as err:  # a file, not a pipe: reading a pipe would wait for workers left holding it
        proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    try:
        deadline = time.monotonic() + 180
        while proc.poll() is None and time.monotonic() < deadline and not list(out.glob("train/*.npz")):
            seen.update((p.pid, p) for p in _descendants(proc.pid))
            time.sleep(0.02)
        assert proc.poll() is None, log.read_text()[-3000:]
        at_stop = [p for p in _descendants(proc.pid) if not _is_resource_tracker(p)]
        seen.update((p.pid, p) for p in at_stop)
        made = len(list(out.glob("train/*.npz")))
        assert len([p for p in at_stop if _alive(p)]) >= 2 and made < 4, "the pool's workers were at work"
        proc.send_signal(signal.SIGTERM)
        status = proc.wait(timeout=60)
        left = [pid for pid, p in seen.items() if not _is_resource_tracker(p) and _alive(p)]
        deadline = time.monotonic() + 3  # the resource tracker ends once its pipe from the command closes
        while time.monotonic() < deadline and any(_alive(p) for p in seen.values()):
            time.sleep(0.05)
        left += [pid for pid, p in seen.items() if _is_resource_tracker(p) and _alive(p)]
        stderr = log.read_text()
        made = len(list(out.glob("train/*.npz")))  # the rooms written stay
        assert status == 128 + signal.SIGTERM, stderr[-3000:]
        assert left == [], f"left running after the command ended: {left}"
        assert "Traceback" not in stderr and "leaked" not in stderr, stderr[-3000:]
        assert stderr.strip().splitlines()[-1].startswith("spread-generate: terminated (SIGTERM)"), stderr[-3000:]
    finally:
        for p in seen.values():
            if _alive(p):
                p.kill()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    again = [a if a != "processes=2" else "processes=1" for a in args]  # the rooms do not depend on it; no pool
    relaunch = subprocess.run(again, env=env, capture_output=True, text=True, timeout=240)
    assert relaunch.returncode == 0, relaunch.stderr[-3000:]
    assert len(list(out.glob("train/*.npz"))) == 4
    import json

    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["counts"]["train"] == 4 and manifest["this_run"]["rooms_generated"] == 4 - made


def test_spread_generate_refuses_asset_categories_it_does_not_know_or_none_by_key_before_any_work():
    """``assets.categories=[nosuch]`` was a KeyError traceback once the library was built, after the log was written;
    ``[]`` was blamed on ``room.min_objects``."""
    from spread.procgen.dataset import DatasetConfig, check_config

    config = DatasetConfig(rooms=2)
    for asked, said in ((["chair", "nosuch"], r"unknown \['nosuch'\]"), ([], "none")):
        config.assets.categories = asked
        with pytest.raises(ValueError, match=rf"^assets\.categories={re.escape(str(asked))}: {said} \(known: .*chair"):
            check_config(config)
    config.assets.categories = ["chair", "bed", "dining_table"]
    check_config(config)


def test_spread_view_prints_an_ipv6_host_in_brackets_so_the_address_opens():
    from spread.cli.view import browser_url

    assert browser_url("::1", 8080) == "http://[::1]:8080/"
    assert browser_url("127.0.0.1", 8080) == "http://127.0.0.1:8080/"
