#!/bin/bash
# What a bare GPU machine lacks, made here in one command before a slot (docs/gpu.md, "A bare GPU machine"):
#   .whl/             wheels for the machine's Python (3.12): diffusers, trimesh, python-fcl, hydra-core, omegaconf,
#                     antlr4 (no wheel on the index: built here), importlib_metadata, zipp — about 12 MB
#   .gpudata/rooms/   ROOMS generated rooms (seed SEED) with only what the pipeline and detect_ab read: the splits,
#                     stats.json, the asset index, meshes, parts and records, and the point caches of the assets the
#                     rooms use (no logs, renders or physics .obj) — about 23 MB for 40 rooms
# Both are git-ignored; a slot carries them: run(carry=[".whl", ".gpudata"], command="bash benchmarks/gpu_slot.sh").
# Usage: bash benchmarks/gpu_carry.sh        (ROOMS=40 SEED=7 PYVER=3.12 BIN=.venv/bin by default)
set -euo pipefail
cd "$(dirname "$0")/.."
ROOMS=${ROOMS:-40}; SEED=${SEED:-7}; PYVER=${PYVER:-3.12}; BIN=${BIN:-.venv/bin}
if [ ! -x "$BIN/python" ]; then
  echo "gpu_carry: needs the project's environment ($BIN/python): run 'make install' first"; exit 1
fi

rm -rf .whl && mkdir -p .whl
"$BIN/python" -m pip download -q --no-deps --only-binary=:all: --python-version "$PYVER" --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
  diffusers==0.42.1 trimesh==5.2.0 python-fcl==0.7.0.11 importlib_metadata zipp hydra-core==1.3.8 omegaconf==2.3.1
"$BIN/pip" wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3

rm -rf .gpudata/rooms && mkdir -p .gpudata
"$BIN/spread-generate" out_dir=.gpudata/rooms rooms="$ROOMS" seed="$SEED" renders=0 > .gpudata/generate.log
"$BIN/python" - .gpudata/rooms <<'EOF'
"""Drop what the GPU rows never read: logs, renders, physics meshes, the caches of assets no room uses."""
import shutil
import sys
from pathlib import Path

import numpy as np

root = Path(sys.argv[1])
used = set()
for split in ("train", "val", "test"):
    for path in (root / split).glob("*.npz"):
        with np.load(path, allow_pickle=False) as scene:
            used |= {str(a) for a in scene["asset_id"]}
for name in ("logs", "renders"):
    shutil.rmtree(root / name, ignore_errors=True)
dropped = 0
for path in (root / "assets" / "cache").iterdir():
    if path.suffix == ".obj" or path.name.split(".")[0] not in used:
        dropped += path.stat().st_size
        path.unlink()
print(f"gpu_carry: {len(used)} assets in use; {dropped / 2**20:.1f} MiB of unused caches and physics meshes dropped")
EOF
du -sh .whl .gpudata/rooms
total=$(du -scm .whl .gpudata | tail -1 | cut -f1)
[ "$total" -lt 60 ] || { echo "gpu_carry: ${total} MiB is over what a device call carries (64 MiB in all)"; exit 1; }
