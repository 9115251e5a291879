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
#   RUN_ID          the rendezvous id and the run folder name, the same on every node and new for every job
#                   (required; under SLURM/PBS the job id when unset). A run folder made with another RUN_ID is
#                   never resumed: resuming means launching again with the same RUN_ID, which resumes the run's
#                   newest checkpoint (its step continues; the log names the file).
#   ATTEMPT         which launch of RUN_ID this is: counted by this script (jobs/env.sh spread_attempt: a launch
#                   after one that started training is the next attempt); set it only to override. The checkpoint
#                   to resume is decided once per attempt, by the first node to arrive, and every node reads that
#                   decision ($OUT/.resume/<attempt>), so all ranks load one file.
#   LOCAL_ADDR      this node's address for the others (default: torchrun looks up the hostname)
#   MAX_RESTARTS    torchrun's restarts of the whole group after a failure (default 0: relaunch the script,
#                   which resumes from the run folder's newest checkpoint)
# The run folder is $SPREAD_RUNS/train/torchrun-$RUN_ID (SPREAD_OUT overrides), on the shared filesystem.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"

: "${NNODES:?set NNODES (number of nodes)}"
: "${RDZV_ENDPOINT:?set RDZV_ENDPOINT=HOST:PORT (the rendezvous, on one of the nodes)}"
NPROC_PER_NODE=${NPROC_PER_NODE:-1}
RUN_ID=${RUN_ID:-${SLURM_JOB_ID:-${PBS_JOBID:-}}}
: "${RUN_ID:?set RUN_ID (a new id for every job, the same on every node; relaunch with the same id to resume)}"
OUT=${SPREAD_OUT:-$SPREAD_RUNS/train/torchrun-$RUN_ID}
mkdir -p "$OUT"
spread_claim_run "$OUT" "$RUN_ID"
spread_tmpdir "$OUT"
export SPREAD_JOB_ID=$RUN_ID
ATTEMPT=${ATTEMPT:-$(spread_attempt "$OUT")}
export SPREAD_ATTEMPT_MARK="$OUT/.resume/$ATTEMPT.started"   # spread-train marks the attempt started
ARGS=("$@" trainer=ddp "trainer.num_nodes=$NNODES" "trainer.devices=$NPROC_PER_NODE" "out_dir=$OUT")
spread_default ARGS "ckpt_path=$(spread_decide_resume "$OUT" "$ATTEMPT")"
echo "torchrun.sh: RUN_ID=$RUN_ID attempt $ATTEMPT, into $OUT"

exec torchrun --nnodes="$NNODES" --nproc-per-node="$NPROC_PER_NODE" --rdzv-backend=c10d \
    --rdzv-endpoint="$RDZV_ENDPOINT" --rdzv-id="$RUN_ID" --max-restarts="${MAX_RESTARTS:-0}" \
    ${LOCAL_ADDR:+--local-addr="$LOCAL_ADDR"} --no-python \
    "$SPREAD_VENV/bin/spread-train" "${ARGS[@]}"
