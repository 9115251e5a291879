"""Training stages of an ablation or comparison as their own processes, through a launcher, so that
Lightning DDP works inside them (in-process, DDP would re-run the whole ablation in every rank).

``train.launcher`` (``conf/ablate.yaml``):

| launcher | the training stage runs | DDP |
|---|---|---|
| ``inprocess`` | in the ablation's process (:class:`~spread.commands.in_process.InProcessCommands`) | no |
| ``local`` | ``python -m spread.cli.train <overrides>`` | ``trainer=ddp trainer.devices=N``: Lightning starts the other ranks |
| ``torchrun`` | ``torchrun --standalone --nproc_per_node=N -m spread.cli.train`` (``--nnodes`` > 1: the rendezvous of ``RDZV_ENDPOINT``, id ``RUN_ID``) | one process per rank |
| ``srun`` | ``srun --nodes=M --ntasks-per-node=N python -m spread.cli.train`` (inside a SLURM allocation) | one task per rank |

The stage's output is the same run folder as in-process; a failing launch raises with the tail of its output.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from spread.commands.in_process import InProcessCommands

LAUNCHERS = ("inprocess", "local", "torchrun", "srun")


def launch_prefix(launcher: str, nproc: int = 1, nnodes: int = 1) -> list[str]:
    """The command line before ``spread-train``'s overrides."""
    python = [sys.executable, "-m", "spread.cli.train"]
    if launcher == "local":
        return python
    if launcher == "torchrun":
        torchrun = str(Path(sys.executable).parent / "torchrun")
        where = ["--standalone"] if nnodes == 1 else [
            f"--nnodes={nnodes}", "--rdzv-backend=c10d", f"--rdzv-endpoint={os.environ['RDZV_ENDPOINT']}",
            f"--rdzv-id={os.environ['RUN_ID']}"]
        return [torchrun, *where, f"--nproc-per-node={nproc}", "-m", "spread.cli.train"]
    if launcher == "srun":
        return ["srun", f"--nodes={nnodes}", f"--ntasks-per-node={nproc}", *python]
    raise ValueError(f"train.launcher={launcher}: choose from {LAUNCHERS}")


class LaunchedCommands(InProcessCommands):
    """:class:`InProcessCommands` whose training stages run through a launcher (module docstring)."""

    def __init__(self, launcher: str, nproc: int = 1, nnodes: int = 1):
        if launcher not in LAUNCHERS:
            raise ValueError(f"train.launcher={launcher}: choose from {LAUNCHERS}")
        self.launcher, self.nproc, self.nnodes = launcher, int(nproc), int(nnodes)

    def train(self, overrides: list[str], run_dir: Path) -> None:
        if self.launcher == "inprocess":
            return super().train(overrides, run_dir)
        cmd = [*launch_prefix(self.launcher, self.nproc, self.nnodes), *overrides]
        env = {**os.environ, "HYDRA_FULL_ERROR": "1"}
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        log = Path(run_dir) / "launch.log"
        log.parent.mkdir(parents=True, exist_ok=True)
        log.write_text(" ".join(cmd) + "\n\n" + proc.stdout + "\n" + proc.stderr)
        if proc.returncode != 0:
            raise RuntimeError(f"{self.launcher} training exited with {proc.returncode} (log: {log}):\n"
                               + (proc.stdout + proc.stderr)[-2000:])
