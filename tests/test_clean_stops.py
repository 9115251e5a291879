"""Clean stops (issue 31 item 4): a command's own Ray cluster ends with it on SIGTERM, and after a SIGKILL the next
session on the same folder stops what the killed one left running — the processes recorded with its Ray session,
never processes found by name."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from spread.runtime.ray import RECORD, leftover_processes, stop_leftover

HOLDER = """
import sys, time
from pathlib import Path
from spread.runtime.ray import RaySettings, ray_session
with ray_session(RaySettings(num_cpus=1, object_store_memory=80 * 1024 * 1024), owner=Path(sys.argv[1])):
    print("ready", flush=True)
    time.sleep(600)
"""


def start_holder(folder: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdout=subprocess.PIPE, text=True,
                            start_new_session=True)
    assert proc.stdout.readline().strip() == "ready"
    return proc


def running(pids, session: str) -> list[int]:
    out = []
    for p in pids:
        try:
            if session in Path(f"/proc/{p}/cmdline").read_bytes().decode(errors="replace"):
                out.append(p)
        except OSError:
            pass
    return out


@pytest.mark.timeout(240)
def test_a_killed_drivers_cluster_is_stopped_by_the_next_session_on_its_folder(tmp_path):
    proc = start_holder(tmp_path)
    record = json.loads((tmp_path / RECORD).read_text())
    assert record["driver_pid"] == proc.pid and {"raylet", "gcs_server"} <= set(record["pids"])
    os.kill(proc.pid, signal.SIGKILL)  # kill -9 of the driver alone
    proc.wait(timeout=30)
    time.sleep(1.0)
    left = leftover_processes(record)
    assert left, "the killed driver's Ray agents outlive it"
    unrelated = subprocess.Popen(["sleep", "60"])  # a process of nobody's Ray session: never touched
    try:
        stopped = stop_leftover(tmp_path)
        assert set(left) <= set(stopped) and unrelated.pid not in stopped
        assert not running(left, record["session_dir"]) and not (tmp_path / RECORD).exists()
        assert unrelated.poll() is None
    finally:
        unrelated.kill()
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


@pytest.mark.timeout(240)
def test_sigterm_stops_the_command_and_its_cluster_and_removes_the_record(tmp_path):
    proc = start_holder(tmp_path)
    record = json.loads((tmp_path / RECORD).read_text())
    own = [p for pids in record["pids"].values() for p in pids]
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    deadline = time.time() + 30
    while time.time() < deadline and running(own, record["session_dir"]):
        time.sleep(0.2)
    assert not running(own, record["session_dir"]) and not (tmp_path / RECORD).exists()


def test_a_record_of_processes_that_are_gone_or_of_another_session_stops_nothing(tmp_path):
    sleeper = subprocess.Popen(["sleep", "60"])
    try:  # a recorded pid reused by another program (its command line names no Ray session): left alone
        (tmp_path / RECORD).write_text(json.dumps({"driver_pid": 1, "session_dir": "/tmp/ray/session_gone_1",
                                                   "pids": {"raylet": [sleeper.pid, 999999999]}}))
        assert stop_leftover(tmp_path) == [] and sleeper.poll() is None and not (tmp_path / RECORD).exists()
        (tmp_path / RECORD).write_text("{not json")  # a damaged record: removed, nothing stopped
        assert stop_leftover(tmp_path) == [] and not (tmp_path / RECORD).exists()
    finally:
        sleeper.kill()
