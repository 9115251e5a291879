#!/usr/bin/env bash
# Ray Train on a Ray cluster: Lightning DDP inside a TorchTrainer, one worker per device (a Ray job running
# spread-train-ray, which composes conf/train.yaml with trainer=ray).
#   jobs/ray_train.sh experiment=paper_geometry data.root=/shared/rooms ray_train.num_workers=8 ray_train.use_gpu=true
#   jobs/ray_train.sh experiment=quick data.root=/shared/rooms ray_train.num_workers=4 ray_train.cpus_per_worker=4
#   jobs/ray_train.sh ... ray_train.max_failures=3      # restart the workers from Ray's newest checkpoint
# The run folder is $SPREAD_RUNS/train/ray-<RUN_ID> (RUN_ID defaults to the time; SPREAD_OUT overrides):
# submitting again with the same RUN_ID resumes from its newest checkpoint.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
RUN_ID=${RUN_ID:-$(date +%Y-%m-%d_%H-%M-%S)}
OUT=${SPREAD_OUT:-$SPREAD_RUNS/train/ray-$RUN_ID}
mkdir -p "$OUT/.tmp"
export SPREAD_JOB_TMPDIR="$OUT/.tmp"   # checkpoints renamed into place on the run folder's filesystem
ARGS=("$@" "out_dir=$OUT")
spread_default ARGS ray_train.address=auto "ckpt_path=$(spread_resume "$OUT")"
spread_submit "$SPREAD_VENV/bin/spread-train-ray" "${ARGS[@]}"
