#!/usr/bin/env bash
# Multi-node Lightning DDP without a scheduler: run this script on every node, with the same settings.
# torchrun starts NPROC_PER_NODE processes per node; the nodes meet at a c10d rendezvous hosted by the
# node that RDZV_ENDPOINT names (ranks are assigned there), and Lightning reads the ranks torchrun sets.
#   on every node:  NNODES=2 NPROC_PER_NODE=4 RDZV_ENDPOINT=node0:29400 RUN_ID=geo1 \
#                   jobs/torchrun.sh experiment=paper_geometry data.root=/shared/rooms trainer.accelerator=gpu
# Settings (environment):
#   NNODES          number of nodes (required)
#   RDZV_ENDPOINT   HOST:PORT of the rendezvous, reachable from every node (required; the host runs the store)
#   NPROC_PER_NODE  processes per node = devices per node (default 1)
#   RUN_ID          the rendezvous id and the run folder name (default spread): the same on every node
#   LOCAL_ADDR      this node's address for the others (default: torchrun looks up the hostname)
#   MAX_RESTARTS    torchrun's restarts of the whole group after a failure (default 0: relaunch the script,
#                   which resumes from the run folder's newest checkpoint)
# The run folder is $SPREAD_RUNS/train/torchrun-$RUN_ID (SPREAD_OUT overrides), on the shared filesystem.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"

: "${NNODES:?set NNODES (number of nodes)}"
: "${RDZV_ENDPOINT:?set RDZV_ENDPOINT=HOST:PORT (the rendezvous, on one of the nodes)}"
NPROC_PER_NODE=${NPROC_PER_NODE:-1}
RUN_ID=${RUN_ID:-spread}
OUT=${SPREAD_OUT:-$SPREAD_RUNS/train/torchrun-$RUN_ID}
mkdir -p "$OUT"
spread_tmpdir "$OUT"
ARGS=("$@" trainer=ddp "trainer.num_nodes=$NNODES" "trainer.devices=$NPROC_PER_NODE" "out_dir=$OUT")
spread_default ARGS "ckpt_path=$(spread_resume "$OUT")"

exec torchrun --nnodes="$NNODES" --nproc-per-node="$NPROC_PER_NODE" --rdzv-backend=c10d \
    --rdzv-endpoint="$RDZV_ENDPOINT" --rdzv-id="$RUN_ID" --max-restarts="${MAX_RESTARTS:-0}" \
    ${LOCAL_ADDR:+--local-addr="$LOCAL_ADDR"} --no-python \
    "$SPREAD_VENV/bin/spread-train" "${ARGS[@]}"
