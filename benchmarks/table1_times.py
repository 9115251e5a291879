"""Where each Table 1 method's time went in one ``spread-compare`` run: one table.

    python benchmarks/table1_times.py runs/compare/quick

Per method: training and sampling wall seconds (the ledger, ``compare.json``) and CPU seconds of the
comparison's process (``compare_times.json``; training and in-process sampling run there on one torch
thread), sampling seconds per scene (``samples/<m>/sampling.json``: batch seconds / scenes written) and the
evaluation's wall seconds (Ray workers, not in the CPU column). The physcene row trains nothing: its
checkpoint is DiffuScene's (``derive/physcene``).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

METHODS = ("atiss", "diffuscene", "physcene", "instructscene", "spread")


def main(out_dir: str) -> None:
    out = Path(out_dir)
    stages = json.loads((out / "compare.json").read_text())["stages"]
    cpu = json.loads((out / "compare_times.json").read_text()) if (out / "compare_times.json").exists() else {}

    def wall(name: str) -> str:
        seconds = (stages.get(name) or {}).get("seconds")
        return "–" if seconds is None else f"{seconds:.1f}"

    def cpu_of(name: str) -> str:
        return "–" if name not in cpu else f"{cpu[name]:.1f}"

    print("| method | train wall s | train CPU s | sample wall s | sample CPU s | s / scene | evaluate wall s |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for m in METHODS:
        manifest = out / "samples" / m / "sampling.json"
        per_scene = "–"
        if manifest.exists():
            data = json.loads(manifest.read_text())
            if data.get("seconds_per_batch") is not None and data.get("written_this_run"):
                per_scene = f"{data['seconds_per_batch'] * data['batches_run'] / data['written_this_run']:.3f}"
        train = "derive/physcene" if m == "physcene" else f"train/{m}"
        print(f"| {m} | {wall(train)} | {cpu_of(train)} | {wall(f'sample/{m}')} | {cpu_of(f'sample/{m}')} | "
              f"{per_scene} | {wall(f'evaluate/{m}')} |")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    main(sys.argv[1])
