"""The launchers in jobs/ against stand-ins: ``srun``, ``scontrol``, ``torchrun``, ``ray`` and the venv's
``spread-*`` / ``python`` are small shell scripts on PATH (a fake venv) that log their arguments, so the scripts'
decisions are checked without SLURM, a GPU or a Ray cluster:

* slurm_train.sbatch run as sbatch does (a spooled copy, from another folder): finds the checkout through
  ``scontrol show job``; devices per node from ``--ntasks`` without ``--ntasks-per-node``; a SIGUSR1 to the
  batch shell reaches the task, which saves ``hpc_ckpt_1.ckpt`` and requeues; the requeued run resumes it;
  another job cannot take the run folder.
* torchrun.sh: no RUN_ID → refused; two "nodes" of one attempt resume the same checkpoint, decided once.
* slurm_ray.sbatch: waits for its nodes by polling (no fixed sleep), port and temp folder per job.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

from spread.configs import conf_dir

JOBS = Path(conf_dir()).parent / "jobs"

SRUN = r"""#!/bin/bash
echo "srun $*" >> "$FAKE_LOG"
out=""; for a in "$@"; do [[ "$a" == out_dir=* ]] && out=${a#out_dir=}; done
if [[ -n "${FAKE_TASK:-}" && -n "$out" ]]; then
    trap 'echo lightning > "$out/hpc_ckpt_1.ckpt"; scontrol requeue "$SLURM_JOB_ID"; exit 0' USR1
    echo started >> "$FAKE_LOG"
    for i in $(seq 600); do sleep 0.1; done
    exit 1
fi
"""
SCONTROL = r"""#!/bin/bash
case "$1" in
  show) if [[ "$2" == hostnames ]]; then echo node0; echo node1; else echo "JobId=$3 JobName=t Command=$FAKE_SCRIPT WorkDir=/"; fi ;;
  requeue) echo "requeue $2" >> "$FAKE_LOG" ;;
esac
"""
LOGGER = """#!/bin/bash
echo "$(basename "$0") $*" >> "$FAKE_LOG"
"""
PYTHON = r"""#!/bin/bash
# readiness poll of spread_wait_ray: alive nodes grow by one per call
n=$(( $(cat "$FAKE_COUNT" 2>/dev/null || echo 0) + 1 )); echo $n > "$FAKE_COUNT"
echo "poll" >> "$FAKE_LOG"
echo $(( n / 2 ))
"""


@pytest.fixture
def stand_ins(tmp_path):
    venv = tmp_path / "venv" / "bin"
    venv.mkdir(parents=True)
    scripts = {"srun": SRUN, "scontrol": SCONTROL, "python": PYTHON, "torchrun": LOGGER, "ray": LOGGER,
               "spread-train": LOGGER, "spread-sample": LOGGER}
    for name, text in scripts.items():
        (venv / name).write_text(text)
        (venv / name).chmod(0o755)
    log = tmp_path / "calls.log"
    env = {"PATH": f"{venv}:{os.environ['PATH']}", "HOME": str(tmp_path), "SPREAD_VENV": str(venv.parent),
           "SPREAD_RUNS": str(tmp_path / "runs"), "FAKE_LOG": str(log), "FAKE_COUNT": str(tmp_path / "count"),
           "SLURM_JOB_NODELIST": "node[0-1]", "SLURM_JOB_NUM_NODES": "2"}
    return {"tmp": tmp_path, "env": env, "log": log}


def spooled(tmp: Path, name: str) -> Path:
    """The script as sbatch runs it: a copy in a spool folder, away from the checkout."""
    spool = tmp / "spool"
    spool.mkdir(exist_ok=True)
    copy = spool / "slurm_script"
    shutil.copy(JOBS / name, copy)
    return copy


def calls(log: Path, prefix: str) -> list[str]:
    return [line for line in log.read_text().splitlines() if line.startswith(prefix)] if log.exists() else []


def test_slurm_train_from_any_folder_with_ntasks_and_a_requeue(stand_ins):
    tmp, log = stand_ins["tmp"], stand_ins["log"]
    script = spooled(tmp, "slurm_train.sbatch")
    env = {**stand_ins["env"], "SLURM_JOB_ID": "4242", "SLURM_NTASKS": "8", "SLURM_SUBMIT_DIR": str(tmp),
           "FAKE_SCRIPT": str(JOBS / "slurm_train.sbatch"), "FAKE_TASK": "1"}
    proc = subprocess.Popen(["bash", str(script), "experiment=quick", "data.root=/d"], cwd=tmp, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 30
    while "started" not in (log.read_text() if log.exists() else "") and time.time() < deadline:
        time.sleep(0.1)
    proc.send_signal(signal.SIGUSR1)  # --signal=B:SIGUSR1@120: the batch shell passes it on to the tasks
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, out
    run = tmp / "runs" / "train" / "slurm-4242"
    (first,) = calls(log, "srun ")
    assert "trainer.devices=4" in first and "trainer.num_nodes=2" in first and f"out_dir={run}" in first
    assert first.endswith("ckpt_path=null") and "job 4242" in out and "node[0-1]" in out
    assert calls(log, "requeue") == ["requeue 4242"] and (run / "hpc_ckpt_1.ckpt").exists()
    # the requeued job: same id, same folder, resumes the checkpoint saved at the signal
    env = {**env, "SLURM_RESTART_COUNT": "1"}
    env.pop("FAKE_TASK")
    done = subprocess.run(["bash", str(script), "experiment=quick", "data.root=/d"], cwd=tmp, env=env,
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert calls(log, "srun ")[-1].endswith(f"ckpt_path={run}/hpc_ckpt_1.ckpt")
    # another job may not take that folder; uneven tasks per node are refused
    other = subprocess.run(["bash", str(script)], cwd=tmp, env={**env, "SLURM_JOB_ID": "5", "SPREAD_OUT": str(run)},
                           capture_output=True, text=True, timeout=60)
    assert other.returncode == 2 and "belongs to run id 4242" in other.stderr
    uneven = subprocess.run(["bash", str(script)], cwd=tmp, env={**env, "SLURM_JOB_ID": "6", "SLURM_NTASKS": "3"},
                            capture_output=True, text=True, timeout=60)
    assert uneven.returncode == 2 and "3 tasks do not divide over 2 nodes" in uneven.stderr


def test_torchrun_needs_a_run_id_and_every_node_resumes_one_checkpoint(stand_ins):
    tmp, log = stand_ins["tmp"], stand_ins["log"]
    env = {k: v for k, v in stand_ins["env"].items() if not k.startswith("SLURM")}
    env.update(NNODES="2", NPROC_PER_NODE="2", RDZV_ENDPOINT="node0:29400")
    refused = subprocess.run(["bash", str(JOBS / "torchrun.sh"), "experiment=quick"], env=env, capture_output=True,
                             text=True, timeout=60)
    assert refused.returncode != 0 and "set RUN_ID" in refused.stderr
    run = tmp / "runs" / "train" / "torchrun-geo1"
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_text("a")
    env["RUN_ID"] = "geo1"
    nodes = [subprocess.Popen(["bash", str(JOBS / "torchrun.sh"), "experiment=quick"], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for _ in range(2)]
    for node in nodes:
        out, _ = node.communicate(timeout=60)
        assert node.returncode == 0, out
    launched = calls(log, "torchrun ")
    assert len(launched) == 2 and all("--rdzv-id=geo1" in c for c in launched)
    assert {c.split("ckpt_path=")[1] for c in launched} == {f"{run}/checkpoints/last.ckpt"}
    assert (run / ".resume" / "1").read_text().strip() == f"{run}/checkpoints/last.ckpt"
    taken = subprocess.run(["bash", str(JOBS / "torchrun.sh")], env={**env, "RUN_ID": "geo2", "SPREAD_OUT": str(run)},
                           capture_output=True, text=True, timeout=60)
    assert taken.returncode == 2 and "belongs to run id geo1" in taken.stderr


def test_slurm_ray_waits_for_its_nodes_with_a_port_and_temp_dir_per_job(stand_ins):
    tmp, log = stand_ins["tmp"], stand_ins["log"]
    script = spooled(tmp, "slurm_ray.sbatch")
    env = {**stand_ins["env"], "SLURM_JOB_ID": "777", "SLURM_CPUS_PER_TASK": "4", "SLURM_SUBMIT_DIR": str(tmp),
           "FAKE_SCRIPT": str(JOBS / "slurm_ray.sbatch")}
    started = time.perf_counter()
    done = subprocess.run(["bash", str(script), "spread-sample", "ckpt=c", "data.root=/d", "out_dir=/o"], cwd=tmp,
                          env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    starts = calls(log, "srun ")
    assert len(starts) == 2 and all("--temp-dir=/tmp/ray_777" in s and "20777" in s for s in starts)
    polls = calls(log, "poll")
    assert len(polls) >= 4  # 2 alive nodes after the 4th poll: it waited for readiness
    assert calls(log, "spread-sample ")[0].endswith("ray.address=node0:20777 progress=false")
    assert time.perf_counter() - started < 60


def test_the_slurm_scripts_outside_slurm_say_to_submit_them_with_sbatch(stand_ins):
    env = {k: v for k, v in stand_ins["env"].items() if not k.startswith("SLURM")}
    for name in ("slurm_train.sbatch", "slurm_ray.sbatch"):
        done = subprocess.run(["bash", str(JOBS / name), "experiment=quick"], env=env, capture_output=True, text=True,
                              timeout=60)
        assert done.returncode == 2 and "submit it with sbatch" in done.stderr, done.stderr
        assert "unbound variable" not in done.stderr


def test_torchrun_counts_its_attempts_itself(stand_ins):
    """A relaunch with the same RUN_ID after an attempt that started training is attempt 2 (it resumes the newest
    checkpoint, decided afresh); a relaunch after one that never started (the rendezvous failed) joins it."""
    tmp, log = stand_ins["tmp"], stand_ins["log"]
    env = {k: v for k, v in stand_ins["env"].items() if not k.startswith("SLURM")}
    env.update(NNODES="1", RDZV_ENDPOINT="node0:29400", RUN_ID="wf2")
    run = tmp / "runs" / "train" / "torchrun-wf2"

    def launch():
        done = subprocess.run(["bash", str(JOBS / "torchrun.sh"), "experiment=quick"], env=env, capture_output=True,
                              text=True, timeout=60)
        assert done.returncode == 0, done.stdout + done.stderr
        return done.stdout, calls(log, "torchrun ")[-1]

    out, call = launch()
    assert "attempt 1" in out and call.endswith("ckpt_path=null")
    out, call = launch()  # attempt 1 never marked started (the stand-in torchrun trains nothing): joined
    assert "attempt 1" in out and call.endswith("ckpt_path=null")
    (run / ".resume" / "1.started").touch()  # what spread-train does once every process runs
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").write_text("a")
    out, call = launch()
    assert "attempt 2" in out and call.endswith(f"ckpt_path={run}/checkpoints/last.ckpt")
    assert (run / ".resume" / "2").read_text().strip() == f"{run}/checkpoints/last.ckpt"
