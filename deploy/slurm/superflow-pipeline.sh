#!/usr/bin/env bash
# One node's pipeline of deploy/slurm/superflow-ddp.sbatch (run by srun, one task per
# node): this host's share of every epoch in shard mode, one stream per trainer rank of
# the node; restarted when it fails; on exit, cleanup of the job's iceoryx2 files.
set -euo pipefail

# Host rank and count: the node's index in the job (one pipeline per node).
export SUPERFLOW_HOST_RANK="${SLURM_NODEID:?run under srun}"
export SUPERFLOW_HOST_COUNT="${SLURM_NNODES:?run under srun}"
: "${SUPERFLOW_IOX_PREFIX:?set by superflow-ddp.sbatch}"
# The trainer ranks on this node: each reads the stream of its local rank.
world="${SUPERFLOW_LOCAL_WORLD_SIZE:?set by superflow-ddp.sbatch}"
bin="${SUPERFLOW_BIN:?}"
restarts="${SUPERFLOW_PIPELINE_RESTARTS:-5}"
# Paths or object-store URLs (s3://...): a store's credentials (AWS_*) come with srun's
# environment.
read -r -a drives <<< "${SUPERFLOW_DRIVES:?}"

pipeline=""
# shellcheck disable=SC2329 # invoked by the EXIT trap
cleanup() {
    if [ -n "$pipeline" ]; then kill -TERM "$pipeline" 2>/dev/null || true; fi
    wait || true
    # Whatever a SIGKILLed process (a pipeline or a trainer rank) left under this job's
    # prefix (node-local).
    rm -f /dev/shm/"${SUPERFLOW_IOX_PREFIX}"_* 2>/dev/null || true
    find /tmp/iceoryx2 -name "${SUPERFLOW_IOX_PREFIX}_*" -delete 2>/dev/null || true
}
trap cleanup EXIT
trap 'exit 143' TERM INT

# Restarted when it fails (the trainers keep their subscription and resume their
# stream); SIGTERM (the trainers are done, or the job ends) stops it: the batch in
# flight finishes and the shared memory is released.
for ((attempt = 0; ; attempt++)); do
    "$bin/superflow-pipeline" --mcap "${drives[@]}" --run "$RUN" \
        --mode shard --world-size "$world" --batch-size "${SUPERFLOW_BATCH_SIZE:-4}" \
        --host-rank "$SUPERFLOW_HOST_RANK" --host-count "$SUPERFLOW_HOST_COUNT" \
        --iox-prefix "$SUPERFLOW_IOX_PREFIX" &
    pipeline=$!
    status=0
    wait "$pipeline" || status=$?
    pipeline=""
    # 0: the configured epochs are streamed.
    if [ "$status" -eq 0 ] || [ "$attempt" -ge "$restarts" ]; then exit "$status"; fi
    echo "node $SUPERFLOW_HOST_RANK: the pipeline exited with $status, restart $((attempt + 1)) of $restarts in 5 s" >&2
    sleep 5
done
