"""How long a console script takes to refuse a bad command line, and whether torch loaded for it: this commit
against an older one, runs alternated so both see the same load.

    python benchmarks/bench_refusal.py [--old 5a30a88] [--rounds 3]

The older commit's ``src`` and ``conf`` are taken with ``git archive`` into a temporary folder and put first on
``PYTHONPATH`` (this checkout's environment, same packages); each refused command line runs in a fresh process in
an empty folder, as a user types it (``spread-sample nosuchkey=1``, a sampler kind that is not there, ...). Prints
one table: per command line, the median wall seconds of each side, new / old, and whether the new side imported
torch. Wall time of whole processes on a shared machine: read the ratio, within one run.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: (console script, arguments): each is refused by its checks before any work.
LINES = [
    ("train", ["nosuchkey=1"]),
    ("train", ["data.root=nodata", "model.variant=nope"]),
    ("sample", ["nosuchkey=1"]),
    ("sample", ["ckpt=a.ckpt", "data.root=d", "out_dir=o", "sampler.kind=nope"]),
    ("sample", ["ckpt=a.ckpt", "data.root=d", "out_dir=o", "sampler.eta=2"]),
    ("evaluate", ["nosuchkey=1"]),
    ("ablate", ["nosuchkey=1"]),
    ("compare", ["nosuchkey=1"]),
    ("report", ["nosuchkey=1"]),
    ("train", ["experiment=quick", "data.root=nodata"]),
    # a multirun: refused ahead now (job #1's eta); before, job #0 ran and failed on the checkpoint that is not there
    ("sample", ["-m", "ckpt=a.ckpt", "data.root=d", "out_dir=o", "sampler.eta=0,2"]),
    # the 27-job grid, every job fine: both sides fail in job #0 on the missing checkpoint (the check's own cost)
    ("sample", ["-m", "+sweep=guidance_grid", "ckpt=a.ckpt", "data.root=d"]),
]

PROBE = """import sys, atexit
atexit.register(lambda: print('TORCH', 'torch' in sys.modules, file=sys.stderr))
sys.argv = ['spread-{command}', *{args!r}]
from spread.cli.{command} import main
main()
"""


def run(command: str, args: list[str], src: Path | None, folder: Path) -> tuple[float, bool, int]:
    """Wall seconds, whether torch was imported, exit status of one refused command line."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["WANDB_MODE"] = "disabled"
    if src is not None:
        env["PYTHONPATH"] = str(src) + os.pathsep + env.get("PYTHONPATH", "")
    start = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", PROBE.format(command=command, args=args)], cwd=folder, env=env,
                         capture_output=True, text=True, timeout=300)
    seconds = time.perf_counter() - start
    return seconds, "TORCH True" in out.stderr, out.returncode


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--old", default="5a30a88", help="the commit to compare with (default: before stop 71)")
    parser.add_argument("--rounds", type=int, default=3)
    a = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_refusal_") as tmp:
        tmp = Path(tmp)
        archive = tmp / "old.tar"
        subprocess.run(["git", "-C", str(REPO), "archive", "-o", str(archive), a.old, "src", "conf"], check=True)
        with tarfile.open(archive) as tar:
            tar.extractall(tmp / "old", filter="data")
        times: dict[tuple, dict[str, list[float]]] = {}
        torch_new: dict[tuple, bool] = {}
        for r in range(a.rounds):
            for i, (command, args) in enumerate(LINES):
                key = (command, " ".join(args))
                for side, src in (("old", tmp / "old" / "src"), ("new", None)):
                    folder = tmp / f"cwd_{side}_{r}_{i}"
                    folder.mkdir()
                    seconds, torch, code = run(command, args, src, folder)
                    if code == 0:
                        raise SystemExit(f"spread-{command} {' '.join(args)} was not refused ({side})")
                    times.setdefault(key, {"old": [], "new": []})[side].append(seconds)
                    if side == "new":
                        torch_new[key] = torch
            print(f"round {r + 1}/{a.rounds} done", file=sys.stderr)
    print(f"| command line | old {a.old} (s) | new (s) | new / old | torch loaded (new) |")
    print("|---|---|---|---|---|")
    for (command, args), sides in times.items():
        old, new = statistics.median(sides["old"]), statistics.median(sides["new"])
        print(f"| `spread-{command} {args}` | {old:.2f} | {new:.2f} | {new / old:.2f} | {torch_new[(command, args)]} |")


if __name__ == "__main__":
    main()
