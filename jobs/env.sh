# Sourced by the scripts in jobs/: the project's environment on whichever node runs them.
#   SPREAD_HOME   the project checkout, the same path on every node (default: the folder above jobs/)
#   SPREAD_VENV   its virtual environment (default: $SPREAD_HOME/.venv), on the shared filesystem or at the
#                 same path on every node; activated here so that spread-*, torchrun and ray are found
#   SPREAD_RUNS   where run folders go (default: $SPREAD_HOME/runs); must be shared by every node
#   WANDB_MODE    offline unless set (compute nodes rarely reach the internet; `wandb sync` uploads later)
SPREAD_HOME=${SPREAD_HOME:-$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)}
SPREAD_VENV=${SPREAD_VENV:-$SPREAD_HOME/.venv}
SPREAD_RUNS=${SPREAD_RUNS:-$SPREAD_HOME/runs}
if [[ ! -x "$SPREAD_VENV/bin/spread-train" ]]; then
    echo "jobs/env.sh: no spread-train in $SPREAD_VENV/bin (set SPREAD_VENV, or: make install)" >&2
    return 1 2>/dev/null || exit 1
fi
export PATH="$SPREAD_VENV/bin:$PATH"
export SPREAD_HOME SPREAD_VENV SPREAD_RUNS
export WANDB_MODE=${WANDB_MODE:-offline}
export PYTHONUNBUFFERED=1

# spread_tmpdir DIR: point TMPDIR at DIR/.tmp (created). Lightning writes a checkpoint to a temporary file
# under TMPDIR and renames it into place; the rename is atomic only on one filesystem, so on a cluster whose
# /tmp is node-local and whose run folders are on a shared filesystem, a checkpoint would otherwise be
# *copied* into place and a kill mid-copy would leave a torn last.ckpt (see jobs/README.md).
spread_tmpdir() {
    export TMPDIR="$1/.tmp"
    mkdir -p "$TMPDIR"
}

# spread_resume OUT: the ckpt_path that resumes OUT's own newest checkpoint (Lightning's SLURM requeue
# checkpoint hpc_ckpt_<n>.ckpt or checkpoints/last.ckpt, whichever is newer), or null for a fresh run.
# (ckpt_path=last would also look at other run folders of the experiment when OUT has none.)
spread_resume() {
    local newest
    newest=$(ls -t "$1"/hpc_ckpt_*.ckpt "$1"/checkpoints/last.ckpt 2>/dev/null | head -n 1 || true)
    echo "${newest:-null}"
}

# spread_default ARRAY KEY=VALUE...: append each KEY=VALUE to the array named ARRAY unless it sets KEY already.
# The scripts put the user's arguments first and their own after them: Hydra takes its flags (--multirun,
# -m, --cfg ...) only before the overrides, and for a key given twice the last value wins.
spread_default() {
    local -n _args=$1
    shift
    local kv a
    for kv in "$@"; do
        for a in "${_args[@]}"; do
            [[ "${a#+}" == "${kv%%=*}="* ]] && continue 2
        done
        _args+=("$kv")
    done
}

# spread_submit COMMAND ARGS...: run COMMAND as a Ray job on the cluster at RAY_ADDRESS (the head's dashboard,
# default http://127.0.0.1:8265: run this on the head node, or forward the port). The command runs on the
# head node, where `ray.address=auto` joins the cluster; paths must be valid there (the same on every node).
# RAY_SUBMIT_OPTS adds options to `ray job submit` (e.g. --no-wait, then `ray job logs -f <id>`); RAY_CLI is
# the ray command (default: the venv's).
# SPREAD_JOB_TMPDIR sets TMPDIR for the job's processes (see spread_tmpdir). SPREAD_SUBMIT=local runs the
# command here instead (debugging a job script on one machine).
spread_submit() {
    local entry
    entry=$(printf '%q ' "$@")
    if [[ "${SPREAD_SUBMIT:-ray}" == local ]]; then
        eval "$entry"
        return
    fi
    local env="\"WANDB_MODE\": \"$WANDB_MODE\", \"PYTHONUNBUFFERED\": \"1\""
    [[ -n "${SPREAD_JOB_TMPDIR:-}" ]] && env="$env, \"TMPDIR\": \"$SPREAD_JOB_TMPDIR\""
    # shellcheck disable=SC2086
    "${RAY_CLI:-ray}" job submit --address "${RAY_ADDRESS:-http://127.0.0.1:8265}" \
        --runtime-env-json "{\"env_vars\": {$env}}" ${RAY_SUBMIT_OPTS:-} -- "$entry"
}

# spread_claim_run OUT RUN_ID: OUT belongs to RUN_ID (OUT/run_id); refuse a folder another run id made, so a new
# job never resumes (or overwrites) another job's checkpoints.
spread_claim_run() {
    local owner
    if [[ -f "$1/run_id" ]]; then
        owner=$(cat "$1/run_id")
        if [[ "$owner" != "$2" ]]; then
            echo "jobs: $1 belongs to run id $owner, not $2: use a new SPREAD_OUT, or RUN_ID=$owner to resume it" >&2
            exit 2
        fi
    else
        echo "$2" > "$1/run_id.tmp.$$" && mv -n "$1/run_id.tmp.$$" "$1/run_id" && rm -f "$1/run_id.tmp.$$"
        [[ "$(cat "$1/run_id")" == "$2" ]] || { echo "jobs: $1 was claimed by run id $(cat "$1/run_id")" >&2; exit 2; }
    fi
}

# spread_attempt OUT: which launch of OUT's run this is, counted here, not by the user. Attempt n is decided once
# (OUT/.resume/n) and marked started (OUT/.resume/n.started) by spread-train once every node has met (after the
# rendezvous, so a node of the same launch always arrives before the mark): a launch finding the newest attempt
# not started joins it, else it is attempt n+1. ATTEMPT=<n> still overrides.
spread_attempt() {
    local dir="$1/.resume" n=0 f
    for f in "$dir"/[0-9]*; do
        [[ -e "$f" ]] || continue
        f=${f##*/}; f=${f%%.*}
        [[ "$f" =~ ^[0-9]+$ ]] && (( f > n )) && n=$f
    done
    if (( n == 0 )); then echo 1
    elif [[ -e "$dir/$n.started" ]]; then echo $(( n + 1 ))
    else echo "$n"
    fi
}

# spread_decide_resume OUT ATTEMPT: the checkpoint this attempt resumes, decided once for every node: the
# first node to create OUT/.resume/ATTEMPT.lock (mkdir is atomic, also on NFS) writes spread_resume's answer
# to OUT/.resume/ATTEMPT (atomic rename); the others wait for that file (SPREAD_RESUME_WAIT s, default 600).
spread_decide_resume() {
    local dir="$1/.resume" file="$1/.resume/$2" waited=0
    mkdir -p "$dir"
    if mkdir "$file.lock" 2>/dev/null; then
        spread_resume "$1" > "$file.tmp.$$"
        mv "$file.tmp.$$" "$file"
    fi
    while [[ ! -f "$file" ]]; do
        (( waited++ >= ${SPREAD_RESUME_WAIT:-600} )) && { echo "jobs: no resume decision in $file" >&2; exit 3; }
        sleep 1
    done
    cat "$file"
}

# spread_job_script: the path of the submitted batch script (sbatch runs a copy from its spool folder), from
# `scontrol show job`; empty when unknown.
spread_job_script() {
    [[ -n "${SLURM_JOB_ID:-}" ]] || return 0
    scontrol show job "$SLURM_JOB_ID" 2>/dev/null | tr ' ' '\n' | sed -n 's/^Command=//p' | head -n 1
}

# spread_wait_ray ADDRESS N TIMEOUT: wait until the Ray cluster at ADDRESS has N alive nodes (polled every 2 s);
# fail after TIMEOUT seconds naming how many came up.
spread_wait_ray() {
    local start=$SECONDS alive=0
    while (( SECONDS - start < $3 )); do
        alive=$("${SPREAD_PYTHON:-$SPREAD_VENV/bin/python}" - "$1" <<'PY' 2>/dev/null || echo 0
import sys, ray
ray.init(address=sys.argv[1], logging_level="ERROR", log_to_driver=False)
print(sum(1 for n in ray.nodes() if n.get("Alive")))
PY
)
        alive=${alive##*$'\n'}
        if (( alive >= $2 )); then
            echo "ray: $alive node(s) alive at $1"
            return 0
        fi
        sleep 2
    done
    echo "ray: only $alive of $2 node(s) alive at $1 after $3 s" >&2
    exit 4
}
