#!/usr/bin/env bash
# spread-sample on a Ray cluster: one sampling actor per worker, spread over the nodes (a Ray job).
#   jobs/ray_sample.sh ckpt=/shared/runs/train/X/checkpoints/last.ckpt data.root=/shared/rooms \
#       out_dir=/shared/runs/sample/X workers=32 samples_per_graph=4
#   jobs/ray_sample.sh ... device=cuda ray.num_gpus_per_worker=1 workers=8 batch_size=64     # one GPU per actor
#   jobs/ray_sample.sh ... guidance=paper                                                  # guided sampling
# Every argument is a spread-sample override (conf/sample.yaml). Resumable: submit it again with the same
# out_dir and it samples only the missing scenes.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
ARGS=("$@")
spread_default ARGS ray.address=auto progress=false
spread_submit "$SPREAD_VENV/bin/spread-sample" "${ARGS[@]}"
