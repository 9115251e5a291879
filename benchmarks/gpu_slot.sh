#!/bin/bash
# One short GPU slot, in order of what is still unmeasured (issue 29), each part under its own time limit so a slot
# that ends early still returns what was measured (everything lands in $OUT, default ./gpu_out):
#   1. spread-train through Lightning with the CUDA-graph'd step (model.compile_mode=reduce-overhead), +Geometry at
#      paper size on the carried rooms: perf/steps_per_s per 10 steps in lightning_metrics.csv;
#   2. the search kernel against an older one (OLD=<file>, see search_ab.py) and with 32 queries a program;
#   3. DDIM-50 sampling at batch 64 (eager, CUDA graph, bf16);
#   4. the guided pipeline on real rooms (DDPM-1000 estimate, refine, paper guidance) at batch 64.
# On a bare machine (docs/gpu.md): carry .whl and .gpudata, then
#   bash benchmarks/gpu_slot.sh            # ROOMS=.gpudata/rooms OLD=.gpudata/old_nearest_dense.py by default
set -u
OUT=${OUT:-gpu_out}; ROOMS=${ROOMS:-.gpudata/rooms}; OLD=${OLD:-.gpudata/old_nearest_dense.py}; PY=${PY:-python3}
mkdir -p "$OUT"
if ! $PY -c "import hydra, diffusers" 2>/dev/null && [ -d .whl ]; then  # a bare machine: the carried wheels
  $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
  export PYTHONPATH=/tmp/site:$PWD/src
fi
export PYTHONUNBUFFERED=1 WANDB_MODE=disabled
T0=$(date +%s)
mark() { echo "== $1 done at $(( $(date +%s) - T0 )) s" | tee -a "$OUT/parts.txt"; }
quiet() { grep -v "^W1\|^ *\^\|━"; }
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv > "$OUT/gpu.txt" 2>&1

timeout "${TRAIN_S:-170}" $PY -m spread.cli.train experiment=paper_geometry data.root="$ROOMS" trainer=gpu \
  logger=csv model.compile=true model.compile_mode=reduce-overhead trainer.max_steps=60 trainer.log_every_n_steps=10 \
  trainer.check_val_every_n_epoch=100000 trainer.num_sanity_val_steps=0 renders.every_n_epochs=0 \
  data.num_workers=4 data.persistent_workers=true out_dir=/tmp/gpu_slot_train 2>&1 | quiet | tail -12
cp /tmp/gpu_slot_train/csv/version_0/metrics.csv "$OUT/lightning_metrics.csv" 2>/dev/null
mark "lightning (reduce-overhead)"

if [ -f "$OLD" ]; then
  timeout 80 $PY benchmarks/search_ab.py --old "$OLD" --block-q 32 --json "$OUT/search_ab.json" 2>&1 | tail -12
  mark "search a/b"
fi

timeout 100 $PY benchmarks/bench_gpu.py --skip-counts --only sample --json "$OUT/sample.json" 2>&1 | quiet | tail -20
mark "sample"

timeout "${PIPELINE_S:-200}" $PY benchmarks/bench_gpu.py --skip-counts --only pipeline --data "$ROOMS" \
  --json "$OUT/pipeline.json" 2>&1 | quiet | tail -20
mark "pipeline"
