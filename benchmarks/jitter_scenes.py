"""Copies of scene files with their translations jittered: stand-ins for imperfect generated scenes.

    python benchmarks/jitter_scenes.py IN_DIR OUT_DIR --sigma 0.05 [--seed 0]

Every object's translation (bbox centre, metres) gets independent N(0, sigma²) noise on each of x, y, z;
rotations, graphs (``spatial``/``physical``, i.e. what the scene is evaluated against), ids and room are
kept, and ``jitter_sigma`` (metres) is stored as an extra array. The noise of a scene is drawn from
``numpy.random.default_rng([seed, k])`` for the k-th file in name order, so a rerun writes the same files.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def jitter_scene(scene, sigma: float, rng: np.random.Generator):
    """A copy of ``scene`` with translations + N(0, sigma²) per axis (metres)."""
    noisy = scene.with_poses(scene.translation + rng.normal(0.0, sigma, scene.translation.shape), scene.rotation)
    noisy.extras["jitter_sigma"] = np.asarray(float(sigma), np.float32)
    return noisy


def jitter_folder(src: Path, dst: Path, sigma: float, seed: int = 0) -> int:
    """Write jittered copies of every scene file of ``src`` into ``dst``; returns how many."""
    from spread.scene import list_scene_files, read_scene, write_scene

    files = list_scene_files(src)
    for k, path in enumerate(files):
        write_scene(jitter_scene(read_scene(path), sigma, np.random.default_rng([seed, k])), dst / path.name)
    return len(files)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("src", type=Path, help="folder of scene files")
    ap.add_argument("dst", type=Path, help="output folder (created)")
    ap.add_argument("--sigma", type=float, default=0.05, help="standard deviation per axis, metres")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    n = jitter_folder(a.src, a.dst, a.sigma, a.seed)
    print(f"wrote {n} scenes jittered by N(0, {a.sigma} m) per axis to {a.dst}")


if __name__ == "__main__":
    main()
