#!/usr/bin/env bash
# The main job on one host: superflow-pipeline streams batches from the given drives
# (default: the sample drive) and one superflow-trainer trains on them.
# Usage: deploy/run-local.sh [DRIVE.mcap|DIR ...]
set -euo pipefail
cd "$(dirname "$0")/.."
drives=("$@")
[ ${#drives[@]} -gt 0 ] || drives=(recordings/drives/street_ros2.mcap)
run="local-$$"

cargo build --release -p superflow-pipeline -p superflow-trainer
./target/release/superflow-pipeline --mcap "${drives[@]}" --run "$run" &
pipeline=$!
trap 'kill "$pipeline" 2>/dev/null || true' EXIT
status=0
./target/release/superflow-trainer --run "$run" || status=$?
wait "$pipeline" || status=$?
exit "$status"
