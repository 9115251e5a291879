#!/bin/bash
# One short GPU slot, in order of what is still unmeasured (issue 29), each part under its own time limit so a slot
# that ends early still returns what was measured (everything lands in $OUT, default ./gpu_out):
#   1. the guidance's triangle pairs on the GPU against the CPU and python-fcl on the same poses (detect_ab.py);
#   2. spread-train through Lightning with the CUDA-graph'd step (model.compile_mode=reduce-overhead), +Geometry at
#      paper size on the carried rooms (2-51 objects: one static graph per bucket of 8 object counts,
#      model.compile_bucket; the fifth slot's run, before the buckets, recompiled per count and never left
#      compiling): perf/steps_per_s per 10 steps in lightning_metrics.csv, Dynamo's recompiles in lightning.log;
#   3. DDIM-50 sampling at batch 64 (eager, CUDA graph, bf16);
#   4. the guided pipeline on real rooms (refine both ways, paper guidance, DDPM-1000) at batch 64;
#   5. where a step's GPU time goes: the top 30 CUDA kernels of one eager training step, base and +Geometry, and of
#      two eager bf16 denoising steps at batch 64 (profile_train.txt; the fifth slot's showed the 107-channel point
#      tokens' LayerNorm and product in slow kernels: padded to 112 channels since).
# (The search a/b of the last slots is done: 32 queries a program won, the default since; OLD=<file> runs it again.)
# The parts' limits (75 + TRAIN_S 280 + 90 + PIPELINE_S 130 + PROFILE_S 75 s) sum to 650 s, over one device call's
# 600: the parts usually end before their limits, and a call cut short loses the last part only (the profile).
# On a bare machine (docs/gpu.md): carry .whl and .gpudata (made here by `bash benchmarks/gpu_carry.sh`), then
#   bash benchmarks/gpu_slot.sh            # ROOMS=.gpudata/rooms by default
set -u
OUT=${OUT:-gpu_out}; ROOMS=${ROOMS:-.gpudata/rooms}; OLD=${OLD:-}; PY=${PY:-python3}
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

timeout 75 $PY benchmarks/detect_ab.py --data "$ROOMS" --scenes 16 --json "$OUT/detect_ab.json" 2>&1 | quiet | tail -12
mark "detect a/b"

TORCH_LOGS=recompiles timeout "${TRAIN_S:-280}" $PY -m spread.cli.train experiment=paper_geometry data.root="$ROOMS" trainer=gpu \
  logger=csv model.compile=true model.compile_mode=reduce-overhead trainer.max_steps=60 trainer.log_every_n_steps=10 \
  trainer.check_val_every_n_epoch=100000 trainer.num_sanity_val_steps=0 renders.every_n_epochs=0 \
  data.num_workers=4 data.persistent_workers=true out_dir=/tmp/gpu_slot_train 2>&1 | quiet > "$OUT/lightning.log"
grep -c "Recompiling function" "$OUT/lightning.log" | sed 's/^/recompiles: /'; tail -8 "$OUT/lightning.log"
cp /tmp/gpu_slot_train/csv/version_0/metrics.csv "$OUT/lightning_metrics.csv" 2>/dev/null
mark "lightning (reduce-overhead)"

if [ -n "$OLD" ] && [ -f "$OLD" ]; then
  timeout 80 $PY benchmarks/search_ab.py --old "$OLD" --block-q 32 --json "$OUT/search_ab.json" 2>&1 | tail -12
  mark "search a/b"
fi

timeout 90 $PY benchmarks/bench_gpu.py --skip-counts --only sample --json "$OUT/sample.json" 2>&1 | quiet | tail -20
mark "sample"

timeout "${PIPELINE_S:-130}" $PY benchmarks/bench_gpu.py --skip-counts --only pipeline --data "$ROOMS" \
  --json "$OUT/pipeline.json" 2>&1 | quiet | tail -20
mark "pipeline"

timeout "${PROFILE_S:-75}" $PY benchmarks/bench_gpu.py --skip-counts --only train sample_profile --profile \
  --profile-out "$OUT/profile_train.txt" --json "$OUT/train_profiled.json" 2>&1 | quiet | tail -6
mark "profile"
