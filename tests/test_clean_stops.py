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


WAITER = """
import sys, time
from pathlib import Path
import ray
from spread.runtime.ray import RaySettings, ray_session
with ray_session(RaySettings(num_cpus=1, object_store_memory=80 * 1024 * 1024), owner=Path(sys.argv[1])):
    slow = ray.remote(lambda: time.sleep(600)).remote()
    print("ready", flush=True)
    ray.wait([slow], num_returns=1)  # the evaluation's and sampling's fan-out wait here
"""


@pytest.mark.timeout(240)
def test_sigterm_while_the_driver_waits_on_ray_exits_as_terminated_not_as_a_failure(tmp_path):
    """Ray's ``wait`` turned the handler's SystemExit(143) into SystemExit(1): ``spread-evaluate`` stopped by SIGTERM
    mid-run exited 1 with no message, as if it had failed."""
    proc = subprocess.Popen([sys.executable, "-c", WAITER, str(tmp_path)], stdout=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(1.0)  # inside ray.wait
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 128 + signal.SIGTERM
        assert not (tmp_path / RECORD).exists()
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


STARTER = """
from spread.runtime.ray import RaySettings, ray_session
with ray_session(RaySettings(num_cpus=1)):
    pass
"""


def _state(pid: int) -> str | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return None


def _gcs_child(pid: int) -> bool:
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/stat") as f:
                parent = int(f.read().rsplit(")", 1)[1].split()[1])
            with open(f"/proc/{entry}/cmdline", "rb") as f:
                if parent == pid and b"gcs_server" in f.read():
                    return True
        except (OSError, ValueError, IndexError):
            continue
    return False


@pytest.mark.timeout(240)
def test_sigterm_to_the_process_group_while_ray_starts_its_cluster_ends_the_command_at_once_and_leaves_no_process():
    """The group's SIGTERM killed the GCS before it published its port, and the driver waited for that port inside
    Ray's code (holding the interpreter: no Python handler runs) for 30 s before it stopped."""
    proc = subprocess.Popen([sys.executable, "-c", STARTER], start_new_session=True)
    try:
        deadline = time.monotonic() + 120
        while not _gcs_child(proc.pid) and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.005)
        assert proc.poll() is None, "the cluster started before the test saw its GCS"
        os.killpg(proc.pid, signal.SIGTERM)
        stopped = time.monotonic()
        assert proc.wait(timeout=60) in (-signal.SIGTERM, 128 + signal.SIGTERM)
        assert time.monotonic() - stopped < 10  # it was 30 s: Ray's wait for the GCS port
        time.sleep(1.0)
        session = subprocess.run(["pgrep", "-s", str(proc.pid)], capture_output=True, text=True).stdout.split()
        left = [p for p in session if _state(int(p)) not in ("Z", None)]  # a zombie no init here reaps is no process
        assert left == [], left
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


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


def _ray_driver_handler(signum, frame):  # what ray.init leaves installed in a driver process
    sys.exit(signum)


@pytest.mark.parametrize("handler", [signal.SIG_DFL, _ray_driver_handler], ids=["lightning", "after_ray_init"])
def test_sigterm_inside_an_in_process_training_stage_stops_the_driver_instead_of_failing_the_stage(tmp_path,
                                                                                                   handler):
    """Found stopping `spread-ablate` mid-training: Lightning turned the SIGTERM into SIGTERMException, the driver
    counted it as the stage's failure and started the next training. Now the command stops (exit 143), the stage is
    neither failed nor recorded, and its begun record stays so a relaunch continues it; a stage's own errors (an
    exception, a command's SystemExit with a message) still fail that stage alone. Whatever handler is in force:
    Lightning's own (SIGTERMException) or the one ray.init leaves in a driver (SystemExit(15)), as in a driver that
    already ran a Ray session."""
    from types import SimpleNamespace

    import lightning.pytorch as pl
    import torch

    from spread.experiments.stages import Ledger, Stage, StageEngine
    from spread.runtime.ray import TERMINATED

    class Tiny(pl.LightningModule):
        def __init__(self):
            super().__init__()
            self.layer = torch.nn.Linear(2, 1)

        def training_step(self, batch, batch_idx):
            if batch_idx == 2:  # the user's `kill <driver pid>`, mid-training
                os.kill(os.getpid(), signal.SIGTERM)
            return self.layer(batch[0]).pow(2).mean()

        def configure_optimizers(self):
            return torch.optim.SGD(self.parameters(), lr=0.1)

    def train(resume: bool) -> None:
        data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.randn(16, 2)), batch_size=2)
        pl.Trainer(max_steps=8, logger=False, enable_checkpointing=False, enable_progress_bar=False,
                   enable_model_summary=False, accelerator="cpu", default_root_dir=tmp_path).fit(Tiny(), data)

    ledger = Ledger(tmp_path / "ledger.json")
    engine = SimpleNamespace(status={}, errors={}, slot=None, ledger=ledger)
    stage = Stage("train/base", tmp_path / "train", [tmp_path / "train" / "last.ckpt"], {"steps": 8}, train)
    previous = signal.signal(signal.SIGTERM, handler)
    try:
        with pytest.raises(SystemExit) as stopped:
            StageEngine.attempt(engine, "train/base", lambda: stage, [])
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert stopped.value.code == TERMINATED
    assert "train/base" not in engine.status and engine.errors == {}  # not a failed stage
    assert ledger.begun("train/base") == {"steps": 8} and ledger.inputs("train/base") is None  # a relaunch continues

    def failing(exc):
        def build():
            raise exc
        return build

    assert StageEngine.attempt(engine, "sample/base", failing(ValueError("bad ckpt")), []) is False
    assert StageEngine.attempt(engine, "evaluate/base", failing(SystemExit("metrics=[nope]: unknown")), []) is False
    assert engine.status == {"sample/base": "failed", "evaluate/base": "failed"}


def test_sigterm_while_a_metric_measures_stops_the_evaluation_instead_of_failing_that_metric(monkeypatch):
    """The per-scene loop keeps going past a metric that fails (its SystemExit too); the SystemExit(143) that SIGTERM
    raises in a Ray session while a metric measures is the command's stop, not that metric's failure."""
    from types import SimpleNamespace

    from spread.evaluation import work
    from spread.runtime.ray import TERMINATED

    def metric(exc):
        def evaluate(scene, library):
            raise exc
        return {"m": SimpleNamespace(evaluate=evaluate)}

    monkeypatch.setattr(work, "read_only_copy", lambda scene: scene)
    assert work.measure(metric(SystemExit("no mesh")), "m", object(), None) == "SystemExit: no mesh"
    assert work.measure(metric(ValueError("bad")), "m", object(), None) == "ValueError: bad"
    with pytest.raises(SystemExit) as stopped:
        work.measure(metric(SystemExit(TERMINATED)), "m", object(), None)
    assert stopped.value.code == 143
