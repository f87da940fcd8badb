#!/usr/bin/env bash
# The main job on one host: superflow-pipeline streams batches from the given drives
# (default: the sample drive) over iceoryx2 and one superflow-trainer receives them.
# Usage: deploy/run-local.sh [DRIVE.mcap|DIR ...]
# The trainer's networks and losses are not built yet: it receives and validates one
# epoch of batches and exits with status 2 saying so.
set -euo pipefail
cd "$(dirname "$0")/.."
drives=("$@")
[ ${#drives[@]} -gt 0 ] || drives=(recordings/drives/street_ros2.mcap)
run="local-$$"
export SUPERFLOW_IOX_PREFIX="${SUPERFLOW_IOX_PREFIX:-sf$$}"

cargo build --release -p superflow-pipeline -p superflow-trainer
./target/release/superflow-pipeline --mcap "${drives[@]}" --run "$run" --epochs 1 &
pipeline=$!
trap 'kill -TERM "$pipeline" 2>/dev/null || true' EXIT
status=0
./target/release/superflow-trainer --run "$run" --steps 2 || status=$?
# The trainer is done: stop the pipeline (SIGTERM: the batch in flight finishes and the
# shared memory is released).
kill -TERM "$pipeline" 2>/dev/null || true
wait "$pipeline" || status=$?
exit "$status"
