#!/usr/bin/env bash
# A guidance-weight sweep on a Ray cluster: one Ray job whose driver runs spread-sample's Hydra multirun over
# the grid of conf/sweep/guidance_grid.yaml (3 x 3 x 3 weights, refine guidance, each run evaluated), one run
# after the other, each sampling and evaluating over the whole cluster.
#   jobs/ray_sweep.sh ckpt=/shared/runs/train/X/checkpoints/last.ckpt data.root=/shared/rooms workers=32
#   jobs/ray_sweep.sh ckpt=... data.root=... guidance.relation=1e-3          # a 3 x 3 slice
#   jobs/ray_sweep.sh ckpt=... data.root=... guidance.collision=0,0.015      # another axis
# Every argument is a spread-sample override. Runs go to $SPREAD_RUNS/sweeps/guidance_grid/c<..>_g<..>_r<..>
# (SPREAD_OUT overrides the sweep folder); resubmitting the same sweep skips the runs that finished.
# Afterwards: spread-report runs=<the sweep folder>.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
OUT=${SPREAD_OUT:-$SPREAD_RUNS/sweeps/guidance_grid}
ARGS=("$@")
spread_default ARGS "sweep_dir=$OUT" ray.address=auto progress=false
spread_submit "$SPREAD_VENV/bin/spread-sample" --multirun +sweep=guidance_grid "${ARGS[@]}"
