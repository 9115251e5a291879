#!/usr/bin/env bash
# spread-evaluate on a Ray cluster: chunks of scenes as Ray tasks over every node (a Ray job).
#   jobs/ray_evaluate.sh scenes=/shared/runs/sample/X/scenes reference=/shared/rooms out_dir=/shared/runs/sample/X/eval
#   jobs/ray_evaluate.sh ... chunk_size=2 protocol.stability_runs=10
# Every argument is a spread-evaluate override (conf/evaluate.yaml). Resumable (out_dir/per_scene.jsonl).
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
ARGS=("$@")
spread_default ARGS ray.address=auto progress=false
spread_submit "$SPREAD_VENV/bin/spread-evaluate" "${ARGS[@]}"
