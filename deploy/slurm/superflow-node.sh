#!/usr/bin/env bash
# One node of deploy/slurm/superflow.sbatch (run by srun, one task per node): the
# pipeline for this host's share and SUPERFLOW_LOCAL_WORLD_SIZE trainers, then cleanup.
set -euo pipefail

# Host rank and count from Slurm: with one task per node the task rank is the node rank.
export SUPERFLOW_HOST_RANK="${SLURM_PROCID:?run under srun}"
export SUPERFLOW_HOST_COUNT="${SLURM_NNODES:?run under srun}"
: "${SUPERFLOW_IOX_PREFIX:?set by superflow.sbatch}"
world="${SUPERFLOW_LOCAL_WORLD_SIZE:-1}"
bin="${SUPERFLOW_BIN:?}"
read -r -a drives <<< "${SUPERFLOW_DRIVES:?}"
read -r -a trainer_args <<< "${TRAINER_ARGS:---config trainer/trainer.toml --backend wgpu --steps 100000}"

pids=()
# shellcheck disable=SC2329 # invoked by the EXIT trap
cleanup() {
    kill -TERM "${pids[@]}" 2>/dev/null || true
    wait || true
    # Whatever a SIGKILLed process left under this job's prefix (node-local).
    rm -f /dev/shm/"${SUPERFLOW_IOX_PREFIX}"_* 2>/dev/null || true
    find /tmp/iceoryx2 -name "${SUPERFLOW_IOX_PREFIX}_*" -delete 2>/dev/null || true
}
trap cleanup EXIT
trap 'exit 143' TERM INT

"$bin/superflow-pipeline" --mcap "${drives[@]}" --run "$RUN" \
    --mode shard --world-size "$world" --batch-size "${SUPERFLOW_BATCH_SIZE:-4}" \
    --host-rank "$SUPERFLOW_HOST_RANK" --host-count "$SUPERFLOW_HOST_COUNT" \
    --iox-prefix "$SUPERFLOW_IOX_PREFIX" &
pipeline=$!
pids+=("$pipeline")

trainers=()
for ((rank = 0; rank < world; rank++)); do
    # --resume always: a requeued job continues from the newest checkpoint (a first
    # start, with none yet, starts fresh).
    "$bin/superflow-trainer" --run "$RUN" --rank "$rank" --world-size "$world" \
        --device-index "$rank" \
        --out "$SUPERFLOW_OUT/host-$SUPERFLOW_HOST_RANK/rank-$rank" --resume \
        --iox-prefix "$SUPERFLOW_IOX_PREFIX" "${trainer_args[@]}" &
    trainers+=("$!")
    pids+=("$!")
done

status=0
for pid in "${trainers[@]}"; do
    wait "$pid" || status=$?
done
# The trainers are done: stop the pipeline (SIGTERM: the batch in flight finishes and
# the shared memory is released).
kill -TERM "$pipeline" 2>/dev/null || true
wait "$pipeline" || true
exit "$status"
