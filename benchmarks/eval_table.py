"""One markdown table from the ``metrics.json`` of several spread-evaluate run folders.

    python benchmarks/eval_table.py LABEL=RUN_DIR [LABEL=RUN_DIR ...]

Columns: Col_mesh (share of objects), GRecall, ASD (mm), Stability, still / displaced < 1 cm / rotated
< 0.1 rad shares, scenes, objects, failed, Stability substeps, wall seconds of the run.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def fmt(value, scale: float = 1.0, digits: int = 4) -> str:
    return "null" if value is None else f"{scale * value:.{digits}f}"


def row(label: str, m: dict) -> str:
    return (f"| {label} | {fmt(m['col_mesh'])} | {fmt(m['grecall'])} | {fmt(m['asd'], 1000, 3)} | "
            f"{fmt(m['stability'])} | {fmt(m['still_fraction'])} | {fmt(m['displacement_ok_fraction'])} | "
            f"{fmt(m['rotation_ok_fraction'])} | {m['n_evaluated']} | {m['n_objects']} | {m['n_failed']} | "
            f"{m['protocol']['stability_substeps']} | {m['run']['seconds']:.0f} |")


def main() -> None:
    print("| scenes | Col_mesh ↓ | GRecall ↑ | ASD mm ↓ | Stability ↑ | still ↑ | moved < 1 cm ↑ "
          "| turned < 0.1 rad ↑ | scenes | objects | failed | substeps | s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for arg in sys.argv[1:]:
        label, _, folder = arg.partition("=")
        print(row(label, json.loads((Path(folder) / "metrics.json").read_text())))


if __name__ == "__main__":
    main()
